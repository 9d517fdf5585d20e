"""Simulation helpers every layer may use: the base class of this project's Python
LeafSystems, a logger for named ports, logs as arrays, a joint reference through
sampled positions, and a simulation loop that shows progress.
"""

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, LeafSystem, OutputPort
from pydrake.systems.primitives import Multiplexer, VectorLogSink
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake import console


class WitnessFreeLeafSystem(LeafSystem):
    """A LeafSystem without witness functions (every system of this project), whose
    per-step cost in a simulation is what its own events and outputs cost.

    Why: after every unrestricted update (a MultibodyPlant's step is one, so every
    step) the Simulator asks each system for its witness functions. For a Python
    LeafSystem pydrake's trampoline looks up a Python override `DoGetWitnessFunctions`;
    LeafSystem does not bind that name, so the look-up fails with an AttributeError,
    formatted and discarded, at every step (about 1 us per system and step, measured
    with scripts/bench_closed_loop.py). pybind11 remembers a method as "not
    overridden" when the attribute it finds is a C++ function: any C++ function does,
    and Drake's own GetWitnessFunctions is the natural one. The trampoline then uses
    Drake's default (no witness functions); it never calls the attribute.
    A subclass that has witness functions overrides DoGetWitnessFunctions as usual.
    """

    DoGetWitnessFunctions = LeafSystem.GetWitnessFunctions


class SampleHold(WitnessFreeLeafSystem):
    """Holds its input (`u`, size k) from one sampling instant to the next (`y`): at
    `offset` (s, in [0, period)) plus every multiple of `period`. Drake's
    ZeroOrderHold with a given value before the first sample (its is zero): a
    controller's reference (or the servo's command) read as the station samples its
    sensors, so that a tick's inputs hold still between two samples."""

    def __init__(
        self, size: int, period: float, offset: float, initial: np.ndarray
    ) -> None:
        """`initial` (k): the output before the first sample, what the other systems'
        initialization events read."""
        super().__init__()
        if not (period > 0 and 0 <= offset < period):
            raise ValueError(
                f"SampleHold: period {period} s must be > 0 and the offset {offset} s "
                "in [0, period)"
            )
        self._u = self.DeclareVectorInputPort("u", size)
        held = self.DeclareDiscreteState(np.array(initial, dtype=float).reshape(size))
        self.DeclareStateOutputPort("y", held)
        self.DeclarePeriodicDiscreteUpdateEvent(period, offset, self._latch)

    def _latch(self, context, state) -> None:
        state.set_value(0, self._u.Eval(context))


@dataclass(frozen=True)
class LoggedPort:
    """Where the samples of one logged port are: rows of a shared VectorLogSink."""

    sink: VectorLogSink
    rows: slice

    def data(self, root_context) -> np.ndarray:
        """The port's samples, (size, samples) like VectorLogSink's log data."""
        return self.sink.FindLog(root_context).data()[self.rows]

    def sample_times(self, root_context) -> np.ndarray:
        return self.sink.FindLog(root_context).sample_times()


def add_loggers(
    builder: DiagramBuilder, ports: dict[str, OutputPort], period: float
) -> dict[str, LoggedPort]:
    """Logs the named vector ports every `period` seconds: one VectorLogSink
    ("log") behind a Multiplexer of all the ports (copies, so the same values as a
    sink per port). One publish event per period for all the ports: at 1 kHz a sink
    per port costs several us per simulated ms (scripts/bench_closed_loop.py)."""
    if not ports:
        return {}
    sizes = [port.size() for port in ports.values()]
    sink = builder.AddNamedSystem("log", VectorLogSink(sum(sizes), period))
    mux = builder.AddNamedSystem("log_multiplexer", Multiplexer(sizes))
    builder.Connect(mux.get_output_port(), sink.get_input_port())
    loggers, start = {}, 0
    for k, (name, port) in enumerate(ports.items()):
        builder.Connect(port, mux.get_input_port(k))
        loggers[name] = LoggedPort(sink, slice(start, start + sizes[k]))
        start += sizes[k]
    return loggers


def logs_to_arrays(
    loggers: dict[str, LoggedPort | VectorLogSink], root_context
) -> dict[str, np.ndarray]:
    """{"t": times, name: (samples, size) array} from `add_loggers`' logs (or from a
    VectorLogSink per name).

    The arrays are copies: a view of a log would keep the whole simulation (log,
    context, Simulator) alive as long as the arrays live."""
    out: dict[str, np.ndarray] = {}
    for name, logger in loggers.items():
        if isinstance(logger, LoggedPort):
            times, data = logger.sample_times(root_context), logger.data(root_context)
        else:
            log = logger.FindLog(root_context)
            times, data = log.sample_times(), log.data()
        if "t" not in out:
            out["t"] = times.copy()
        out[name] = data.T.copy()
    return out


def joint_reference(
    times: np.ndarray, positions: np.ndarray, start: float = 0.0
) -> PiecewisePolynomial:
    """A C2 cubic spline through (times + start, positions), held before and after.

    Args:
        times: (m,) sample times (s), increasing.
        positions: (m, n) joint positions (rad).
        start: time shift (s); the first sample is held on [0, start].
    """
    times = np.asarray(times, float) - times[0] + start
    positions = np.asarray(positions, float)
    if start > 0:
        times = np.concatenate([[0.0], times])
        positions = np.vstack([positions[:1], positions])
    zero = np.zeros((positions.shape[1], 1))
    return PiecewisePolynomial.CubicWithContinuousSecondDerivatives(
        times, positions.T, zero, zero
    )


def run_with_progress(
    simulator: Simulator,
    duration: float,
    label: str,
    stream=None,
    steps: int = 10,
    on_step: Callable[[float], None] | None = None,
) -> float:
    """Advances `simulator` by `duration`, printing progress (one updating line on a
    terminal, a line per step otherwise, in the console's format: `console.line`);
    returns the real-time factor (simulated seconds per wall-clock second)."""
    stream = stream or sys.stderr
    t0 = simulator.get_context().get_time()
    wall0 = time.perf_counter()
    simulator.Initialize()
    tty = stream.isatty()
    prefix = "\r" if tty else ""
    for k in range(1, steps + 1):
        simulator.AdvanceTo(t0 + duration * k / steps)
        wall = time.perf_counter() - wall0
        message = (
            f"{label}: {duration * k / steps:6.2f}/{duration:.2f} s simulated, "
            f"{duration * k / steps / max(wall, 1e-9):5.2f}x real time"
        )
        # One write per line: whole lines when processes share the stream.
        stream.write(
            prefix + console.line(message) + ("" if tty and k < steps else "\n")
        )
        stream.flush()
        if on_step is not None:
            on_step(simulator.get_context().get_time())
    return duration / max(time.perf_counter() - wall0, 1e-9)
