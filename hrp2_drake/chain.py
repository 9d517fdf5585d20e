"""A chain of steps declared once, as a table of rows, and its two shells.

A `Row` says everything a step of the chain is: its name, how its step and its
LeafSystem are made, its inputs by port name, each from a named signal (a station
signal `station/<port>`, a reference `reference/<name>`, or another row's output
`<row>/<output>`), how those inputs make the arguments of its `step`, its outputs
(step state arrays) and the signals it logs. A `Chain` is the rows in the order a
tick runs them, the position command they produce and the references they read.

Both shells are built from the table, by one function each:

- `add_chain`: the Diagram, one LeafSystem a row (`hrp2_drake.step.StepSystem`),
  each input port connected to its source; a selection of entries is a Drake
  `Selector` (entries copied, no arithmetic), a sum an `Adder`;
- `FusedChain`: every row's step in one flat state vector and one ordered plan of
  calls, for the fused controller (`hrp2_drake.control.fused`), with no Drake
  systems at all; an argument that is a contiguous run of signals is a view, any
  other selection one `take` a row.

The timing rule (`hrp2_drake.step`), enforced here once: a row reads the outputs of
the rows above it as computed in this tick; an input from a row below it (a loop) is
allowed only from an output that row declares `held` (its LeafSystem's committed
state, the previous tick's), else `Chain` refuses the table.
"""

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from pydrake.systems.framework import DiagramBuilder, LeafSystem, OutputPort
from pydrake.systems.primitives import Adder, Selector, SelectorParams

from hrp2_drake.step import Step

#: The scopes of a signal that are not rows: the robot's sensors and the references.
STATION, REFERENCE = "station", "reference"


def _split(signal: str) -> tuple[str, str]:
    scope, sep, name = signal.partition("/")
    if not sep or not scope or not name:
        raise ValueError(f"chain: signal '{signal}' is not '<scope>/<name>'")
    return scope, name


@dataclass(frozen=True)
class Take:
    """An input made of entries of signals, concatenated in order: each piece is a
    signal and its entries (None: all of them). `name` names the Diagram's Selector
    (not part of equality: equal Takes share one)."""

    pieces: tuple[tuple[str, tuple[int, ...] | None], ...]
    name: str = field(default="", compare=False)

    def signals(self) -> list[str]:
        return [signal for signal, _ in self.pieces]

    def whole_signal(self) -> str:
        """The one signal this takes whole, or "" if it selects or concatenates."""
        if len(self.pieces) == 1 and self.pieces[0][1] is None:
            return self.pieces[0][0]
        return ""


@dataclass(frozen=True)
class Sum:
    """An input that is the sum of signals of one size (an `Adder`)."""

    signals: tuple[str, ...]
    name: str = field(default="", compare=False)


Source = Take | Sum


def whole(signal: str) -> Take:
    """The whole signal."""
    return Take(((signal, None),))


def entries(signal: str, rows: Sequence[int], name: str = "") -> Take:
    """The entries `rows` of a signal, in that order."""
    return Take(((signal, tuple(int(r) for r in rows)),), name)


def concatenated(*signals: str, name: str = "") -> Take:
    """The signals whole, one after the other."""
    return Take(tuple((s, None) for s in signals), name)


def merged(base: str, size: int, signal: str, rows: Sequence[int], name: str) -> Take:
    """`base` (size entries) with its entries `rows` replaced by `signal`'s, in order
    (a whole robot's command from the controlled joints')."""
    source = {i: (base, i) for i in range(size)}
    source |= {int(row): (signal, k) for k, row in enumerate(rows)}
    pieces: list[tuple[str, list[int]]] = []
    for i in range(size):
        s, k = source[i]
        if pieces and pieces[-1][0] == s:
            pieces[-1][1].append(k)
        else:
            pieces.append((s, [k]))
    return Take(tuple((s, tuple(ks)) for s, ks in pieces), name)


@dataclass(frozen=True)
class Arg:
    """One argument of a step's `step` (or `initialize`): the row's inputs `ports`,
    concatenated, reshaped to `shape` (None: flat). Without ports: None, or an empty
    array if it has a shape (`Arg((), (-1,))`: a concatenation of no inputs)."""

    ports: tuple[str, ...] = ()
    shape: tuple[int, ...] | None = None


def args(*ports: str) -> tuple[Arg, ...]:
    """One argument per port, each the port's input as it is."""
    return tuple(Arg((port,)) for port in ports)


@dataclass(frozen=True)
class Row:
    """One step of a chain (module docstring).

    Args:
        name: the row's name: the scope of its outputs (`<name>/<output>`) and the
            fused controller's attribute for its step.
        system_name: its LeafSystem's name in a Diagram.
        make_step: makes its `Step`.
        make_system: makes its LeafSystem (a `StepSystem` around the same step
            arithmetic), whose input ports are `inputs`' keys and whose output ports
            are `outputs`' keys.
        inputs: each input port's source, in the order of the system's ports.
        outputs: each output's step state array (`Step.rows`), or None for a port
            of the system that no state array holds (computed from the inputs); a
            sequence of names: each output the array of its name.
        arguments: the step's `step(t, *arguments)`, each made of inputs (None: one
            argument per input, in order).
        logged: the signals the chain logs from this row: name -> source (of
            this row's outputs, or the rows above it).
        held: the outputs a row above reads, one tick late (a loop).
        initialize: the arguments of the step's `initialize` (None: it has none),
            after t if `timed_initialize`.
        event: an event kind recorded when `step` returns a non-zero code (0: none);
            with `event_state`, only when the code differs from that state array's
            value before the tick (a fault recorded when it starts or changes).
    """

    name: str
    system_name: str
    make_step: Callable[[], Step]
    make_system: Callable[[], LeafSystem]
    inputs: dict[str, Source]
    outputs: dict[str, str | None] | Sequence[str]
    arguments: tuple[Arg, ...] | None = None
    logged: dict[str, Source] = field(default_factory=dict)
    held: frozenset[str] = frozenset()
    initialize: tuple[Arg, ...] | None = None
    timed_initialize: bool = True
    event: int = 0
    event_state: str = ""

    def __post_init__(self):
        if not isinstance(self.outputs, dict):
            object.__setattr__(self, "outputs", {o: o for o in self.outputs})
        if self.arguments is None:
            object.__setattr__(self, "arguments", args(*self.inputs))


@dataclass(frozen=True)
class Chain:
    """The rows of a chain in the order a tick runs them (module docstring).

    Args:
        rows: the rows.
        command: the position command the chain sends (every joint), or None (a
            chain that commands nothing: the estimation alone).
        references: the references the rows read (`reference/<name>`), name ->
            size, in the order of the fused controller's reference buffer.
    """

    rows: tuple[Row, ...]
    command: Source | None
    references: dict[str, int]

    def __post_init__(self):
        position = {row.name: k for k, row in enumerate(self.rows)}
        if len(position) != len(self.rows):
            raise ValueError("chain: two rows of one name")
        for k, row in enumerate(self.rows):
            for port, source in row.inputs.items():
                for signal in _signals_of(source):
                    self._check_signal(signal, k, row, port, position)
            for arg in row.arguments + (row.initialize or ()):
                unknown = [p for p in arg.ports if p not in row.inputs]
                if unknown:
                    raise ValueError(f"chain: row '{row.name}': no inputs {unknown}")

    def _check_signal(self, signal, k, row, port, position) -> None:
        scope, name = _split(signal)
        where = f"chain: row '{row.name}', input '{port}'"
        if scope == REFERENCE and name not in self.references:
            raise ValueError(f"{where}: unknown reference '{name}'")
        if scope in (STATION, REFERENCE):
            return
        if scope not in position:
            raise ValueError(f"{where}: no row '{scope}'")
        source_row = self.rows[position[scope]]
        if name not in source_row.outputs:
            raise ValueError(f"{where}: row '{scope}' has no output '{name}'")
        if position[scope] >= k and name not in source_row.held:
            raise ValueError(
                f"{where} reads '{signal}', computed later in the tick: a loop must "
                "read a held output (the previous tick's)"
            )

    def row(self, name: str) -> Row | None:
        return next((row for row in self.rows if row.name == name), None)

    def logged(self) -> dict[str, Source]:
        """The logged signals, "q_cmd" (the command, if any) first, then the rows'
        in order."""
        out: dict[str, Source] = {} if self.command is None else {"q_cmd": self.command}
        for row in self.rows:
            out |= row.logged
        return out


def _signals_of(source: Source) -> list[str]:
    return source.signals() if isinstance(source, Take) else list(source.signals)


# ---------------------------------------------------------------------- the Diagram


@dataclass
class ChainSystems:
    """What `add_chain` added: each row's system by row name, the logged signals'
    ports by name ("q_cmd" first) and `port(signal)` for any other."""

    systems: dict[str, LeafSystem]
    logged: dict[str, OutputPort]
    port: Callable[[str], OutputPort]


def add_chain(
    builder: DiagramBuilder, chain: Chain, signals: dict[str, OutputPort]
) -> ChainSystems:
    """Adds one LeafSystem per row of `chain` and connects every input to its source:
    `signals` gives the station's and the references' ports by signal name
    (`station/<port>`, `reference/<name>`); a row's output is its system's port."""
    systems = {
        row.name: builder.AddNamedSystem(row.system_name, row.make_system())
        for row in chain.rows
    }

    def port(signal: str) -> OutputPort:
        scope, name = _split(signal)
        if scope in systems:
            return systems[scope].GetOutputPort(name)
        if signal not in signals:
            raise KeyError(f"add_chain: no port for the signal '{signal}'")
        return signals[signal]

    made: dict[Source, OutputPort] = {}

    def source_port(source: Source, name: str) -> OutputPort:
        if isinstance(source, Take) and source.whole_signal():
            return port(source.whole_signal())
        if source not in made:
            made[source] = _add_source(builder, source, source.name or name, port)
        return made[source]

    for row in chain.rows:
        system = systems[row.name]
        for name, source in row.inputs.items():
            builder.Connect(
                source_port(source, f"{row.system_name}_{name}"),
                system.GetInputPort(name),
            )
    logged = {
        name: source_port(source, name) for name, source in chain.logged().items()
    }
    return ChainSystems(systems, logged, port)


def _add_source(builder, source: Source, name: str, port) -> OutputPort:
    """A Selector for a Take, an Adder for a Sum, named `name`."""
    if isinstance(source, Sum):
        ports = [port(s) for s in source.signals]
        adder = builder.AddNamedSystem(name, Adder(len(ports), ports[0].size()))
        for k, p in enumerate(ports):
            builder.Connect(p, adder.get_input_port(k))
        return adder.get_output_port()
    inputs = list(dict.fromkeys(source.signals()))
    ports = [port(s) for s in inputs]
    P = SelectorParams
    selections = []
    for signal, rows in source.pieces:
        k = inputs.index(signal)
        rows = range(ports[k].size()) if rows is None else rows
        selections += [
            P.OutputSelection(input_port_index=k, input_offset=r) for r in rows
        ]
    selector = builder.AddNamedSystem(
        name,
        Selector(
            P(
                inputs=[
                    P.InputPortParams(name=s.replace("/", "_"), size=p.size())
                    for s, p in zip(inputs, ports)
                ],
                outputs=[P.OutputPortParams(name="y0", selections=selections)],
            )
        ),
    )
    for k, p in enumerate(ports):
        builder.Connect(p, selector.get_input_port(k))
    return selector.get_output_port()


# ---------------------------------------------------------------------- fused


class FusedChain:
    """Every row's step of a chain in one flat state vector and one plan of calls
    (module docstring).

    `sources` holds, in one buffer: the steps' state (`state`), then the external
    signals in the order given (the station's, then the references), so that every
    argument is either a view on it or one `take` of its rows.

    Args:
        chain: the table.
        external: the station's signals and the references, (signal, size) each,
            in the buffer's order.
        record: called as record(t, event kind, code) for a row's event.
    """

    def __init__(
        self,
        chain: Chain,
        external: Sequence[tuple[str, int]],
        record: Callable[[float, int, int], None],
    ):
        self.chain = chain
        self.steps: dict[str, Step] = {row.name: row.make_step() for row in chain.rows}
        size = sum(step.state_size for step in self.steps.values())
        total = size + sum(n for _, n in external)
        self.sources = np.zeros(total)
        self.state = self.sources[:size]
        #: Each signal's rows of `sources`.
        self._rows: dict[str, slice] = {}
        start = 0
        for row in chain.rows:
            step = self.steps[row.name]
            step.bind(self.state[start : start + step.state_size])
            for output, array in row.outputs.items():
                if array is None:
                    continue
                rows = step.rows(array)
                self._rows[f"{row.name}/{output}"] = slice(
                    start + rows.start, start + rows.stop
                )
            start += step.state_size
        for signal, n in external:
            self._rows[signal] = slice(start, start + n)
            start += n
        self.initial_state = self.state.copy()
        self._record = record
        self._resolved: dict[str, dict[Arg, object]] = {}
        self._plan = [self._plan_row(row) for row in chain.rows]

    def view(self, signal: str) -> np.ndarray:
        """The rows of `sources` of a signal (a view)."""
        if signal not in self._rows:
            raise KeyError(f"FusedChain: no signal '{signal}'")
        return self.sources[self._rows[signal]]

    def indices(self, source: Take) -> np.ndarray:
        """The rows of `sources` a Take reads, in order."""
        out = []
        for signal, rows in source.pieces:
            span = self._rows.get(signal)
            if span is None:
                raise KeyError(f"FusedChain: no signal '{signal}'")
            whole_rows = np.arange(span.start, span.stop)
            out.append(whole_rows if rows is None else whole_rows[list(rows)])
        return np.concatenate(out) if out else np.zeros(0, dtype=int)

    def _plan_row(self, row: Row) -> "_Call":
        """A row's call: its step and arguments, and what fills them first."""
        gathered: list[tuple[Arg, np.ndarray]] = []
        resolved: dict[Arg, object] = {}
        sums = []
        for arg in dict.fromkeys(row.arguments + (row.initialize or ())):
            if not arg.ports:
                resolved[arg] = None if arg.shape is None else np.zeros(0)
                continue
            sources = [row.inputs[p] for p in arg.ports]
            if any(isinstance(s, Sum) for s in sources):
                if len(sources) != 1:
                    raise ValueError(
                        f"FusedChain: row '{row.name}': a sum is a whole argument"
                    )
                views = [self.view(s) for s in sources[0].signals]
                buffer = np.zeros(views[0].size)
                sums.append((buffer, views))
                resolved[arg] = buffer
                continue
            rows = np.concatenate([self.indices(s) for s in sources])
            if rows.size and np.array_equal(
                rows, np.arange(rows[0], rows[0] + rows.size)
            ):
                value = self.sources[rows[0] : rows[0] + rows.size]
                resolved[arg] = value if arg.shape is None else value.reshape(arg.shape)
            else:
                gathered.append((arg, rows))
        take = None
        if gathered:
            rows = np.concatenate([r for _, r in gathered])
            buffer = np.zeros(rows.size)
            start = 0
            for arg, r in gathered:
                value = buffer[start : start + r.size]
                resolved[arg] = value if arg.shape is None else value.reshape(arg.shape)
                start += r.size
            take = (rows, buffer)
        step = self.steps[row.name]
        event_view = step.state[step.rows(row.event_state)] if row.event_state else None
        self._resolved[row.name] = resolved
        return _Call(
            step,
            tuple(resolved[a] for a in row.arguments),
            take,
            sums,
            tuple(resolved[a] for a in row.initialize or ()),
            row.event,
            event_view,
        )

    def argument(self, row_name: str, port: str) -> tuple[np.ndarray, Callable | None]:
        """The argument of a row's step that is its input `port` alone (a view, or
        the buffer its take or sum fills), and what recomputes it from `sources` now
        (None for a view)."""
        value = self._resolved[row_name][Arg((port,))]
        k = next(k for k, row in enumerate(self.chain.rows) if row.name == row_name)
        take, sums = self._plan[k].take, self._plan[k].sums
        if any(buffer is value for buffer, _ in sums):
            views = next(views for buffer, views in sums if buffer is value)
            return value, lambda: self._gather(None, [(value, views)])
        if take is not None and _within(value, take[1]):
            return value, lambda: self._gather(take, [])
        return value, None

    def _gather(self, take, sums) -> None:
        if take is not None:
            self.sources.take(take[0], 0, take[1], "clip")
        for buffer, views in sums:
            buffer[:] = views[0]
            for view in views[1:]:
                buffer += view

    def initialize(self, t: float) -> None:
        """Every row's `initialize` (in order, each from its inputs now)."""
        for row, call in zip(self.chain.rows, self._plan):
            if row.initialize is None:
                continue
            self._gather(call.take, call.sums)
            step, init = call.step, call.initialize
            if row.timed_initialize:
                step.initialize(t, *init)
            else:
                step.initialize(*init)

    def tick(self, t: float) -> None:
        """One tick: each row's step, in order, on the arguments of this tick (the
        hot path: `_gather` inlined)."""
        sources = self.sources
        for step, arguments, take, sums, _, event, event_view in self._plan:
            if take is not None:
                sources.take(take[0], 0, take[1], "clip")
            for buffer, views in sums:
                buffer[:] = views[0]
                for view in views[1:]:
                    buffer += view
            if not event:
                step.step(t, *arguments)
                continue
            previous = event_view[0] if event_view is not None else 0.0
            code = step.step(t, *arguments)
            if code and (event_view is None or code != previous):
                self._record(t, event, code)

    def logged_rows(self, source: Source) -> list[slice] | np.ndarray:
        """The rows of `state` a logged signal reads: the slices to add (a Sum, or a
        contiguous Take: one slice), or the indices of a Take."""
        if isinstance(source, Sum):
            return [self._rows[s] for s in source.signals]
        rows = self.indices(source)
        if rows.size and np.array_equal(rows, np.arange(rows[0], rows[0] + rows.size)):
            return [slice(int(rows[0]), int(rows[0]) + rows.size)]
        return rows


class _Call(NamedTuple):
    """A row's call in a tick (`FusedChain`): `take` (rows of `sources`, the buffer
    they fill, or None) and `sums` ((buffer, views) each) fill its gathered and summed
    arguments before `step.step(t, *arguments)`; `initialize`: its `initialize`'s
    arguments; `event` and `event_view`: `Row.event` and its `event_state` array."""

    step: Step
    arguments: tuple
    take: tuple[np.ndarray, np.ndarray] | None
    sums: list[tuple[np.ndarray, list[np.ndarray]]]
    initialize: tuple
    event: int
    event_view: np.ndarray | None


def _within(view: np.ndarray, buffer: np.ndarray) -> bool:
    """Whether `view` is a view on `buffer`."""
    return view.base is buffer or (view.base is not None and view.base is buffer.base)
