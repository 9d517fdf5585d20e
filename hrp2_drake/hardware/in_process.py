"""The fused controller on the simulated robot in one process, with the loops'
timing and no wire: `run_in_process` (the LCM loop's: sample k is tick k) and
`run_on_bus_in_process` (the bus loop's, call for call). What the loops are tested
against (tests/test_fused.py, tests/test_lcm.py, tests/test_dynamixel_loop.py), and
the benchmarks' closed-loop tick. The sensor buffer's rows come from the controller's
layout (`FusedController.layout`).
"""

import numpy as np

from hrp2_drake.control.fused import FusedController
from hrp2_drake.hardware.messages import SignalCodec


def run_in_process(
    station_config,
    controller: FusedController,
    reference,
    ticks: int,
    on_tick=None,
    com_reference=None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The fused controller on the simulated station in one process, without messages,
    with the LCM loop's timing: the station's sample k (k >= 0; 0 at initialization,
    as the robot's bridge sends it) is the controller's tick at t = k period as its
    encoder message's stamp says it (whole µs: `SignalCodec.elapsed`, bitwise the
    LCM link's t), and the command is applied at once. What the message-driven loop
    is tested against (tests/test_fused.py, tests/test_lcm.py with a lock-step
    robot), and the bench's closed-loop tick (`on_tick(tick)` wraps each tick: a
    timer). With a balance chain, `com_reference` (9 rows) is evaluated at each tick
    into its `com_ref`, as the control loop does (None: `com_ref` stays as the
    caller set it). Returns (q_cmd, τ̂) per tick."""
    from pydrake.systems.analysis import Simulator

    from hrp2_drake.robot.station import initial_joint_positions, make_station

    robot = station_config.description()
    period = station_config.sensors_config().period
    station = make_station(station_config)
    simulator = Simulator(station)
    context = simulator.get_mutable_context()
    layout = controller.layout
    buffer = controller.sensor_buffer
    # The station's sensor ports (and its stamps, if the controller takes them),
    # each with its rows of the controller's sensor buffer.
    sensors = [
        (station.GetOutputPort(name), buffer[rows])
        for name, rows in layout.signals().items()
    ]
    if layout.num_stamps:
        sensors.append((station.GetOutputPort("sensor_time"), controller.sensor_time))
    q_cmd_port = station.GetInputPort("q_cmd")
    q_cmd_port.FixValue(context, initial_joint_positions(station_config))
    command = np.zeros(len(robot.joints))
    simulator.Initialize()
    out = []
    for k in range(ticks):
        if k:
            simulator.AdvanceTo(k * period)
        for port, rows in sensors:
            rows[:] = port.Eval(context)
        t = SignalCodec.elapsed(SignalCodec.stamp_of(k * period), 0)
        _tick_in_process(
            controller, reference, t, k == 0, on_tick, command, com_reference
        )
        q_cmd_port.FixValue(context, command)
        out.append((command.copy(), controller.estimator.tau.copy()))
    return out


def _tick_in_process(
    controller: FusedController,
    reference,
    t: float,
    first: bool,
    on_tick,
    command: np.ndarray,
    com_reference=None,
) -> None:
    """One tick of an in-process run at t (s): the reference at t (and the CoM
    reference's, if given), the chain's initialization on the `first`, the tick and
    its command into `command`, wrapped by `on_tick(step)` if given (a timer)."""
    controller.q_ref[:], controller.v_ref[:], controller.vdot_ref[:] = reference.at(t)
    if com_reference is not None:
        controller.com_ref[:] = com_reference.value(t)[:, 0]
    if first:
        controller.initialize(t)

    def step():
        controller.tick(t)
        controller.command(controller.q_ref, command)

    (on_tick or (lambda tick: tick()))(step)


def run_on_bus_in_process(
    station_config,
    controller: FusedController,
    reference,
    ticks: int,
    on_tick=None,
    on_period=None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The fused controller on the simulated robot's servos (`SimulatedServos`) in one
    process, without a wire, with the bus loop's timing: what `BusLink` and a
    lock-step emulator (`hardware.sim_servo`) do, call for call.

    Start-up at robot time 0, as `ServoBus.start`: the P gain set
    (`position_loop.gain`), the present pose read (through the goal register's
    pulses) and made the goal, torque on. Then period k: the servos sample at k·T,
    one tick at t = k·T, and the command, in pulses, reaches them at k·T + d (d: the
    bus's `read_to_write`). `on_tick(step)` wraps each tick (a timer).
    `on_period(servos, t)`, if given, is called at the start of each period, before
    the servos sample: the robot's side of an experiment (a push on the arm:
    `SimulatedServos.set_external_force`, held from t on; ground truth read for
    evaluation), as `sim-servo`'s faults act at their time. Returns (q_cmd, τ̂) per
    tick.
    """
    from hrp2_drake.robot.bus_servos import SimulatedServos

    servos = SimulatedServos(station_config)
    robot = servos.robot
    bus = robot.bus
    period = station_config.sensors_config().period
    delay = bus.timing().read_to_write
    servos.set_gain(robot.position_loop.gain)
    servos.set_goal(bus.quantized(servos.present().position))
    servos.set_enabled(np.ones(len(robot.joints)))
    command = np.zeros(len(robot.joints))
    out = []
    for k in range(ticks):
        t = k * period
        servos.advance_to(t)
        if on_period is not None:
            on_period(servos, t)
        controller.q_measured[:] = bus.quantized(servos.present().position)
        controller.q_measured_time[:] = t
        _tick_in_process(controller, reference, t, k == 0, on_tick, command)
        servos.advance_to(t + delay)
        servos.set_goal(bus.quantized(command))
        out.append((command.copy(), controller.estimator.tau.copy()))
    return out
