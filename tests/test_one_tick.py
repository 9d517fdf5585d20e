"""One tick from sample to command (issue 34), measured as a user would: a step in one
sensor signal at tick k, and the first tick at which each signal of the chain differs
from the same run without the step, in every shell (the separate LeafSystems, the
fused controller as a LeafSystem, the fused controller as the hardware loop runs it).

The sensors come from a station of held samples (one value per period, what a
sampler holds), so that the step lands exactly on a tick and nothing else moves.
"""

import numpy as np
import pytest
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import PassThrough, TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.assembly.builders import (
    JointReference,
    build_torque_control,
    torque_chain_parts,
)
from hrp2_drake.assembly.torque_control import TorqueControlConfig
from hrp2_drake.control.fused import ControllerLayout, FusedController
from hrp2_drake.robot.ground_truth import true_motor_model
from hrp2_drake.robot.station import StationConfig
from hrp2_drake.simulation import SampleHold, add_loggers, logs_to_arrays

IIWA = StationConfig(robot="iiwa14", scenario="fixed_base")
TICKS = 60  # simulated ticks
STEP_TICK = 40  # the tick whose sample steps
SIGNALS = ("q_cmd", "feedback_position", "tau_estimated")


def _samples(robot, period: float, signal: str, size: float) -> dict[str, np.ndarray]:
    """Every sensor port's samples (TICKS + 1, rows), constant but for `signal`'s
    first entry, which steps by `size` at STEP_TICK ("" for no step)."""
    layout = ControllerLayout.of_robot(robot, stamped=True)
    q0 = np.asarray(robot.home_positions(), float)
    rows = {"q_measured": q0}
    for name in layout.signals():
        if name.startswith("wrench_"):
            rows[name] = np.array([0.1, -0.2, 0.05, 1.0, -2.0, 12.0])
        elif name == "imu_linear_acceleration":
            rows[name] = np.array([0.0, 0.0, 9.81])
        elif name == "imu_angular_velocity":
            rows[name] = np.zeros(3)
    # A little noise, the same in every run: a sensor that repeats its sample
    # exactly is stale to the supervisor.
    noise = np.random.default_rng(0)
    out = {
        name: value + 1e-4 * noise.standard_normal((TICKS + 1, value.size))
        for name, value in rows.items()
    }
    if signal:
        out[signal][STEP_TICK:, 0] += size
    times = period * np.arange(TICKS + 1)
    out["sensor_time"] = np.tile(times[:, None], (1, layout.num_stamps))
    return out


def _sample_station(robot, period: float, samples: dict[str, np.ndarray]):
    """A station Diagram of held samples: each port's sample k from k·period on; a
    q_cmd input that goes nowhere."""
    builder = DiagramBuilder()
    sink = builder.AddNamedSystem("servo", PassThrough(len(robot.joints)))
    builder.ExportInput(sink.get_input_port(), "q_cmd")
    # Sample k from half a period before its instant: the hold reads it there
    # whatever the rounding of k·period.
    times = period * (np.arange(TICKS + 2) - 0.5)
    for name, values in samples.items():
        held = np.vstack([values, values[-1:]]).T
        source = builder.AddNamedSystem(
            f"{name}_samples",
            TrajectorySource(PiecewisePolynomial.ZeroOrderHold(times, held)),
        )
        hold = builder.AddNamedSystem(
            f"{name}_sampler", SampleHold(values.shape[1], period, 0.0, values[0])
        )
        builder.Connect(source.get_output_port(), hold.get_input_port())
        builder.ExportOutput(hold.get_output_port(), name)
    return builder.Build()


def _setup():
    robot = IIWA.description()
    period = robot.sensors.period
    config = TorqueControlConfig(start_time=0.0)
    reference = JointReference.hold(np.asarray(robot.home_positions(), float), 1.0)
    return robot, period, config, reference, true_motor_model(robot)


def _run_diagram(signal: str, size: float, fused: bool) -> dict[str, np.ndarray]:
    robot, period, config, reference, model = _setup()
    station = _sample_station(robot, period, _samples(robot, period, signal, size))
    control = build_torque_control(
        robot, station, reference, model, config, control_period=period, fused=fused
    )
    builder = DiagramBuilder()
    diagram = builder.AddSystem(control.diagram)
    ports = {name: diagram.GetOutputPort(name) for name in SIGNALS}
    loggers = add_loggers(builder, ports, period)
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(period * (TICKS + 0.5))
    logs = logs_to_arrays(loggers, simulator.get_context())
    # A publish at k·period comes before the updates at that instant: it shows the
    # outputs of the sample held until then, k - 1.
    return {name: logs[name][1:] for name in SIGNALS}


def _run_loop(signal: str, size: float) -> dict[str, np.ndarray]:
    """The fused controller as the hardware loop runs it: sample k, tick k, its
    command."""
    robot, period, config, reference, model = _setup()
    parts = torque_chain_parts(robot, reference, model, config, period=period)
    controller = FusedController(parts)
    samples = _samples(robot, period, signal, size)
    layout = controller.layout
    out = {name: [] for name in SIGNALS}
    q_cmd = np.zeros(len(robot.joints))
    for k in range(TICKS):
        for name, rows in layout.signals().items():
            controller.sensor_buffer[rows] = samples[name][k]
        controller.sensor_time[:] = samples["sensor_time"][k]
        t = k * period
        controller.q_ref[:], controller.v_ref[:], controller.vdot_ref[:] = reference.at(
            t
        )
        if k == 0:
            controller.initialize(t)
        controller.tick(t)
        out["q_cmd"].append(controller.command(controller.q_ref, q_cmd).copy())
        signals = controller.signals()
        for name in SIGNALS[1:]:
            out[name].append(signals[name].copy())
    return {name: np.array(rows) for name, rows in out.items()}


def _run(shell: str, signal: str, size: float) -> dict[str, np.ndarray]:
    if shell == "loop":
        return _run_loop(signal, size)
    return _run_diagram(signal, size, fused=shell == "fused")


def delays(shell: str, signal: str, size: float) -> dict[str, int | None]:
    """Ticks from a step in `signal` at STEP_TICK to the first change of each of
    SIGNALS (None: no change within the run)."""
    base, stepped = _run(shell, "", 0.0), _run(shell, signal, size)
    out = {}
    for name in SIGNALS:
        changed = np.abs(stepped[name] - base[name]).max(axis=1) > 1e-12
        assert not changed[:STEP_TICK].any(), f"{name} changed before the step"
        ticks = np.flatnonzero(changed)
        out[name] = int(ticks[0]) - STEP_TICK if ticks.size else None
    return out


@pytest.mark.parametrize("shell", ["separate", "fused", "loop"])
def test_a_step_in_the_encoders_reaches_the_command_in_its_tick(shell):
    measured = delays(shell, "q_measured", 0.002)
    assert measured["q_cmd"] == 0
    assert measured["feedback_position"] == 0


@pytest.mark.parametrize("shell", ["separate", "fused", "loop"])
def test_a_step_in_a_wrench_reaches_the_estimate_and_the_command_in_its_tick(shell):
    robot = IIWA.description()
    measured = delays(shell, f"wrench_{robot.force_sensor}", 5.0)
    assert measured["tau_estimated"] == 0
    assert measured["q_cmd"] == 0


if __name__ == "__main__":  # the delays of every path, in periods
    robot = IIWA.description()
    for signal, size in (("q_measured", 0.002), (f"wrench_{robot.force_sensor}", 5.0)):
        for shell in ("separate", "fused", "loop"):
            print(signal, shell, delays(shell, signal, size))
