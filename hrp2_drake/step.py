"""Per-tick steps: the arithmetic of one discrete system, written once, outside Drake.

A `Step` holds its state as named float64 arrays packed in one flat vector
(`Step.state`), and its `step(...)` maps input arrays to that state in place. Its
outputs are named state arrays. A step holds no systems Context (a MultibodyPlant
context as a computation workspace is fine), allocates nothing per tick, and never
logs: it counts events in its state and its shell reports them. Its arithmetic is a
numba kernel (`hrp2_drake.kernels`), which `warm_up` compiles before a loop starts.

The timing rule, written once: one tick from sample to command. At tick k every
step reads what its upstream steps computed at tick k, from the station's samples
of tick k and the reference at their instant; a step in a loop (the disturbance
observer, the delay predictor: both read the Δq controller's output and feed it)
is read by its consumer one tick late. The delays left are the filters' own (their
window) and one sample between the command and the servo, as on a real robot. A
chain's table (`hrp2_drake.chain.Chain`) enforces it: it refuses a row that reads a
row below it, but through an output that row holds.

Two shells run the same steps:

- the step's LeafSystem (`StepSystem`): one discrete state group per named array,
  the committed state, so that Drake's Context stays the state's owner (several
  contexts, simulator resets, `FixValue` in tests). Its outputs run the step on the
  inputs as they are now (direct feedthrough, cached) and a periodic event at the
  station's sampling instants commits that tick; a loop's outputs are the committed
  state (`held`), which breaks the algebraic loop;
- the fused controller (`hrp2_drake.control.fused`): every step's state in one flat
  vector (`Step.bind`), the steps run in the chain's order in one update, or in a
  hardware loop with no Drake at all.
"""

from collections.abc import Iterator

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.systems.framework import Context, DiscreteValues, ValueProducer

from hrp2_drake.simulation import WitnessFreeLeafSystem


class Step:
    """Base of a per-tick step (module docstring).

    A subclass declares its state in `__init__` with `_declare(name, initial)` and then
    calls `_finalize()`; each named array is then the attribute `name`, a view on
    `state` (reshaped to `initial`'s shape). Keep the views' names: `bind` re-points
    them.
    """

    def __init__(self) -> None:
        self._layout: list[tuple[str, slice, tuple[int, ...]]] = []
        self._initial: list[np.ndarray] = []
        self._size = 0
        self._state = np.zeros(0)

    def _declare(self, name: str, initial) -> None:
        """Declares the state array `name` with its initial value (any shape)."""
        if any(name == entry[0] for entry in self._layout) or name.startswith("_state"):
            raise ValueError(f"{type(self).__name__}: state '{name}' declared twice")
        value = np.array(initial, dtype=float)
        shape = value.shape if value.ndim else (1,)
        size = int(np.prod(shape))
        self._layout.append((name, slice(self._size, self._size + size), shape))
        self._initial.append(value.reshape(-1) if value.ndim else value.reshape(1))
        self._size += size

    def _finalize(self) -> None:
        """Allocates the state at its initial values and makes the views."""
        state = np.zeros(self._size)
        for (_, rows, _), value in zip(self._layout, self._initial):
            state[rows] = value
        self._state = state
        self._make_views()

    def _make_views(self) -> None:
        for name, rows, shape in self._layout:
            setattr(self, name, self._state[rows].reshape(shape))
        self._views_changed()

    def _views_changed(self) -> None:
        """Called whenever the named arrays became new views (after `_finalize` and
        `bind`): a subclass that keeps derived views (a list of rows, a reshaped
        block) rebuilds them here."""

    @property
    def state(self) -> np.ndarray:
        """The whole state, one flat float64 vector (the named arrays are views)."""
        return self._state

    @property
    def state_size(self) -> int:
        return self._size

    def initial_state(self) -> np.ndarray:
        """The state at construction (a new array)."""
        state = np.zeros(self._size)
        for (_, rows, _), value in zip(self._layout, self._initial):
            state[rows] = value
        return state

    def layout(self) -> Iterator[tuple[str, slice]]:
        """(name, rows of `state`) of each named array, in declaration order."""
        return ((name, rows) for name, rows, _ in self._layout)

    def rows(self, name: str) -> slice:
        """The rows of `state` that hold the named array."""
        for entry, rows, _ in self._layout:
            if entry == name:
                return rows
        raise KeyError(f"{type(self).__name__} has no state '{name}'")

    def bind(self, buffer: np.ndarray) -> None:
        """Moves the state into `buffer` (a flat float64 array of `state_size`, e.g. a
        slice of a fused controller's state): its current values are copied there and
        every named array becomes a view on it."""
        if buffer.shape != (self._size,) or buffer.dtype != np.float64:
            raise ValueError(
                f"{type(self).__name__}.bind: a float64 vector of {self._size} entries "
                f"is needed, got {buffer.dtype} {buffer.shape}"
            )
        buffer[:] = self._state
        self._state = buffer
        self._make_views()

    def reset(self) -> None:
        """Back to the initial state (in place)."""
        self._state[:] = self.initial_state()

    def warm_up(self) -> None:
        """Compiles (or loads from numba's cache) every kernel the step calls per
        tick (`hrp2_drake.kernels`): each called once on arrays of the real types and
        layouts, the step's state left as it was. A step without kernels: nothing."""


def sampling_offset(period: float, lead: float, where: str) -> float:
    """The offset (s) of the sampling instants `lead` before each multiple of
    `period`: the station's sensor sampler's, the commits of a tick and the held
    references'. One expression, so that their events fall at the same float times
    (Drake's event times are offset + k·period). A ValueError naming `where` unless
    0 <= lead < period."""
    if not 0.0 <= lead < period:
        raise ValueError(
            f"{where}: sample lead {lead} s must be >= 0 and shorter than the period "
            f"({period} s)"
        )
    return (period - lead) % period


def new_sample(context: Context, sample_time_group: int) -> bool:
    """Whether a commit event in `context` falls at a new sampling instant: after the
    time of the sample held (the discrete state group `sample_time_group`), not at
    the initialization's instant, whose sample the initialization read."""
    held = context.get_discrete_state(sample_time_group).get_value()[0]
    return context.get_time() > held


class StepSystem(WitnessFreeLeafSystem):
    """A LeafSystem shell around one `Step` that computes a tick in the tick its
    samples arrive (the module docstring's timing rule).

    The committed state: one discrete state group per named state array, and the time
    of the sample now shown (`sample_time`). A cache entry (`ticked`) runs the step on
    a copy of the committed state with the inputs as they are now: the outputs
    declared with `_declare_step_output` are its rows (direct feedthrough from every
    input), those declared `held=True` the committed state (no feedthrough: what
    breaks a loop, one tick late). A periodic event at the sampling instants
    (`_declare_commit`) commits the cached tick, the one of the sample shown until
    then, and the new sample's time. A subclass implements `_tick(context, t)`: read
    the inputs, call its step's `step(t, ...)` (the base loads the step's state before
    and keeps it after)."""

    def _declare_step_state(self, step: Step) -> None:
        """Declares the step's state groups, the sample time and the tick's cache
        entry (call once in `__init__`, after the input ports)."""
        self._step = step
        self._step_groups: list[tuple[int, np.ndarray]] = []
        self._group_of: dict[str, int] = {}
        for name, rows in step.layout():
            group = int(self.DeclareDiscreteState(step.state[rows].copy()))
            self._step_groups.append((group, step.state[rows]))
            self._group_of[name] = group
        self._rows_of = dict(step.layout())
        # The groups a tick reads (a subclass whose step rewrites some of its state
        # every tick may narrow it to the others).
        self._tick_loads = self._step_groups
        self._sample_time = int(self.DeclareDiscreteState(1))
        self.DeclareInitializationDiscreteUpdateEvent(self._latch_sample_time)
        model = AbstractValue.Make(np.zeros(step.state_size))
        self._ticked = self.DeclareCacheEntry(
            "ticked",
            ValueProducer(allocate=model.Clone, calc=self._calc_ticked),
            {self.xd_ticket(), self.all_input_ports_ticket()},
        )

    def _declare_commit(self, period: float, lead: float = 0.0) -> None:
        """The commit at every sampling instant: `lead` (s, in [0, period)) before
        each multiple of `period`, the station's sensor sampler's schedule, declared
        as the sampler declares it (`sampling_offset`), so that Drake's event times are
        the same floats; an instant at the initialization's time commits nothing
        (its sample is the one the initialization read)."""
        self.DeclarePeriodicDiscreteUpdateEvent(
            period, sampling_offset(period, lead, type(self).__name__), self._commit
        )

    def _declare_step_output(
        self, port_name: str, state_name: str = "", held: bool = False
    ):
        """An output port of the named step array (default: the port's name): this
        tick's value (direct feedthrough), or with `held` the committed one."""
        name = state_name or port_name
        if held:
            from pydrake.systems.framework import DiscreteStateIndex

            group = DiscreteStateIndex(self._group_of[name])
            return self.DeclareStateOutputPort(port_name, group)
        rows = self._rows_of[name]
        ticked = self._ticked
        return self.DeclareVectorOutputPort(
            port_name,
            rows.stop - rows.start,
            lambda context, output: output.SetFromVector(ticked.Eval(context)[rows]),
            {ticked.ticket()},
        )

    def _tick(self, context: Context, t: float) -> None:
        """One tick of the step (its state loaded) at the sample time t (s), from the
        inputs in `context`."""
        raise NotImplementedError

    def ticked(self, context: Context) -> np.ndarray:
        """The step's state after the tick of the sample now shown (read-only)."""
        return self._ticked.Eval(context)

    def _calc_ticked(self, context: Context, value: AbstractValue) -> None:
        state = context.get_discrete_state()
        for group, view in self._tick_loads:
            view[:] = state.get_value(group)
        t = context.get_discrete_state(self._sample_time).get_value()[0]
        self._tick(context, t)
        value.get_mutable_value()[:] = self._step.state

    def _commit(self, context: Context, state: DiscreteValues) -> None:
        if not new_sample(context, self._sample_time):
            return
        ticked = self._ticked.Eval(context)
        for name, rows in self._rows_of.items():
            state.set_value(self._group_of[name], ticked[rows])
        state.get_mutable_value(self._sample_time)[0] = context.get_time()

    def _latch_sample_time(self, context: Context, state: DiscreteValues) -> None:
        state.get_mutable_value(self._sample_time)[0] = context.get_time()

    def step_group(self, name: str) -> int:
        """The discrete state group of the named step array."""
        return self._group_of[name]

    def _load(self, state: DiscreteValues) -> None:
        for group, view in self._step_groups:
            view[:] = state.get_value(group)

    def _store(self, state: DiscreteValues) -> None:
        for group, view in self._step_groups:
            state.set_value(group, view)

    def _load_context(self, context) -> None:
        """The step's state from a context (to evaluate something outside an update)."""
        self._load(context.get_discrete_state())
