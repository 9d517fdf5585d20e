"""The fused controller (hrp2_drake/control/fused.py) against the diagram of separate
systems, and the message-driven loop (hardware/control_loop.py, the robot's side in
hardware/robot_bridge.py) over memq:// against
the fused controller in process: the same steps, the same signals."""

from dataclasses import replace

import numpy as np
import pytest
from pydrake.common.yaml import yaml_load_typed
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.assembly.builders import (
    build_torque_control,
    simulated_station,
    torque_chain_parts,
)
from hrp2_drake.assembly.torque_control import (
    ControllerSettings,
    EstimatorSettings,
    ObserverSettings,
    TorqueControlConfig,
)
from hrp2_drake.control.fused import FusedController
from hrp2_drake.hardware.control_loop import ControlLoop
from hrp2_drake.hardware.in_process import run_in_process
from hrp2_drake.hardware.lcm_link import LcmLink
from hrp2_drake.hardware.lcm_station import LcmChannels
from hrp2_drake.hardware.robot_bridge import RobotBridge
from hrp2_drake.hardware.transport import DrakeLcmTransport
from hrp2_drake.robot.ground_truth import true_motor_model
from hrp2_drake.robot.station import StationConfig
from hrp2_drake.simulation import add_loggers, logs_to_arrays
from hrp2_drake.tools.control import ControlConfig, control_reference

HRP2 = StationConfig()
IIWA = StationConfig(robot="iiwa14", scenario="fixed_base")


def _tuned() -> TorqueControlConfig:
    config = yaml_load_typed(
        schema=TorqueControlConfig,
        filename=str(HRP2.description().path("torque_control_k6_0.1.yaml")),
        defaults=TorqueControlConfig(),
    )
    return replace(config, start_time=0.5)


CASES = {
    # The tuned controller: per-signal windows, observer, supervisor, IMU, 4 F/T.
    "hrp2": (HRP2, _tuned, 2.0, None),
    # A force task at the iiwa's wrist sensor, the observer, the supervisor.
    "iiwa_force": (
        IIWA,
        lambda: TorqueControlConfig(
            start_time=0.5,
            estimator=EstimatorSettings(window=41),
            controller=ControllerSettings(
                k6=0.3, force_frame="ft_sensor_link", kf=[0.5]
            ),
            observer=ObserverSettings(disturbance_observer=20.0),
        ),
        2.0,
        PiecewisePolynomial(np.array([0, 0, 0, 0, 0, 5.0]).reshape(6, 1)),
    ),
    # The predictor and the latched fallback, e_q from the filtered q̂.
    "hrp2_predictor": (
        HRP2,
        lambda: TorqueControlConfig(
            supervised=False,
            start_time=0.5,
            estimator=EstimatorSettings(window=41),
            controller=ControllerSettings(k6=1.0, position_source="estimate"),
            observer=ObserverSettings(predictor=True),
        ),
        0.8,
        None,
    ),
}


def _run(case: str, fused: bool) -> dict[str, np.ndarray]:
    station, make, duration, force = CASES[case]
    config = ControlConfig(robot=station.robot, duration=duration)
    reference = control_reference(config)
    extra = {"force_reference": force} if force is not None else {}
    robot, simulated, period = simulated_station(station)
    control = build_torque_control(
        robot,
        simulated,
        reference,
        true_motor_model(robot),
        make(),
        control_period=period,
        fused=fused,
        **extra,
    )
    builder = DiagramBuilder()
    diagram = builder.AddSystem(control.diagram)
    loggers = add_loggers(
        builder, {n: diagram.GetOutputPort(n) for n in control.output_names()}, 0.001
    )
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(duration)
    return logs_to_arrays(loggers, simulator.get_context())


@pytest.mark.slow
@pytest.mark.parametrize("case", list(CASES))
def test_fused_controller_equals_the_separate_systems(case):
    separate, fused = _run(case, fused=False), _run(case, fused=True)
    assert sorted(separate) == sorted(fused)
    for name in separate:
        np.testing.assert_allclose(
            fused[name], separate[name], rtol=0, atol=1e-12, err_msg=name
        )
    # Not a trivial run: torque control drove the controlled joints.
    assert np.abs(separate["delta_q"]).max() > 1e-4
    assert np.abs(separate["tau_estimated"]).max() > 1.0


@pytest.mark.slow
@pytest.mark.parametrize("station_config", [IIWA, HRP2], ids=["iiwa", "hrp2"])
def test_message_driven_loop_over_memq_equals_the_fused_controller(station_config):
    config = ControlConfig(robot=station_config.robot, duration=1.0)
    robot = station_config.description()
    reference = control_reference(config)
    motor_model = true_motor_model(robot)

    def parts():
        return torque_chain_parts(
            robot, reference, motor_model, config.torque_control, period=config.period()
        )

    ticks = 900
    direct = run_in_process(station_config, FusedController(parts()), reference, ticks)

    # The robot's bridge and the controller's loop on one memq:// LCM, in lock step.
    transport = DrakeLcmTransport("memq://")
    bridge = RobotBridge(station_config, transport)
    controller = FusedController(parts())
    controller.warm_up()
    link = LcmLink(robot, transport, LcmChannels(), controller, wait_timeout=1.0)

    def pump():
        while transport.handle(0.0):
            pass

    bridge.step()  # the robot's first messages: the controller's first period
    pump()
    link.connect(controller)
    loop = ControlLoop(controller, link, reference, duration=1.0)
    for k in range(ticks):
        if k:
            bridge.step()
        assert loop.step(0.0)
        pump()
    assert loop.ticks == ticks and loop.refused == 0
    signals = loop.signals()
    for k in range(ticks):
        np.testing.assert_allclose(
            signals["q_cmd"][k], direct[k][0], rtol=0, atol=1e-12
        )
    np.testing.assert_allclose(
        loop.controller.estimator.tau, direct[-1][1], rtol=0, atol=1e-12
    )
    # The robot applied each command in the period it answered.
    np.testing.assert_array_equal(
        bridge.signals()["q_cmd"][1:], signals["q_cmd"][: ticks - 1]
    )
    # Torque control took over (the supervisor's ramp completed).
    assert loop.controller.torque_active() == 1.0


def test_the_layout_names_the_station_rows_once():
    """The fused controller's layout gives the station's sensor ports in its order
    and sizes, the IMU's two signals in one channel, a stamp per signal; the
    LeafSystem reads them in one port, the stamps in another."""
    from hrp2_drake.control.fused import ControllerLayout, FusedTorqueController
    from hrp2_drake.robot.station import sensor_sizes

    robot = HRP2.description()
    config = ControlConfig(robot=HRP2.robot, duration=1.0)
    parts = torque_chain_parts(
        robot,
        control_reference(config),
        true_motor_model(robot),
        config.torque_control,
        period=config.period(),
    )
    layout = FusedController(parts).layout
    assert layout == ControllerLayout.of_robot(robot, stamped=True)
    sizes = sensor_sizes(robot)
    signals = layout.signals()
    assert list(signals) == list(sizes)
    assert [s.stop - s.start for s in signals.values()] == list(sizes.values())
    N, k = len(robot.joints), len(robot.sensor_names())
    assert (layout.values, layout.stamps) == (
        slice(N, N + 6 + 6 * k),
        slice(N + 6 + 6 * k, N + 6 + 6 * k + 3 + k),
    )
    channels = layout.channels()
    assert [c.signals for c in channels][:2] == [
        ("q_measured",),
        ("imu_linear_acceleration", "imu_angular_velocity"),
    ]
    stamp = layout.stamps.start
    assert channels[1].rows == slice(N, N + 6)
    assert channels[1].stamp_rows == slice(stamp + 1, stamp + 3)
    assert channels[2].stamp_rows == slice(stamp + 3, stamp + 4)
    assert layout.q_measured_stamp == slice(stamp, stamp + 1)
    system = FusedTorqueController(parts)
    count = system.num_input_ports()
    inputs = [system.get_input_port(i).get_name() for i in range(count)]
    assert inputs[:2] == ["sensors", "sensor_time"]
    assert system.GetInputPort("sensors").size() == layout.values.stop
    # Unstamped (no supervisor): no stamp rows anywhere.
    bare = ControllerLayout.of_robot(robot, stamped=False)
    assert bare.size == N + 6 + 6 * k
    assert all(c.stamp_rows.start == c.stamp_rows.stop for c in bare.channels())


def test_a_layout_with_a_wrong_number_of_stamps_is_refused():
    from hrp2_drake.control.fused import ControllerLayout

    message = r"^ControllerLayout: 2 sensor stamps for 4 signals"
    with pytest.raises(ValueError, match=message):
        ControllerLayout(
            num_joints=7, has_imu=True, sensor_names=("wrist",), num_stamps=2
        )


@pytest.mark.slow
def test_an_unsupervised_controller_runs_on_every_shell():
    """Without a supervisor the controller takes no stamps (`layout.num_stamps` 0):
    the LCM loop and the in-process runs leave the stamps out instead of writing a
    row that does not exist (an IndexError before the layout), and agree."""
    config = ControlConfig(robot=IIWA.robot, duration=1.0)
    torque_control = replace(config.torque_control, supervised=False)
    robot = IIWA.description()
    reference = control_reference(config)
    motor_model = true_motor_model(robot)

    def controller():
        parts = torque_chain_parts(
            robot, reference, motor_model, torque_control, period=config.period()
        )
        return FusedController(parts)

    ticks = 200
    direct = run_in_process(IIWA, controller(), reference, ticks)
    transport = DrakeLcmTransport("memq://")
    bridge = RobotBridge(IIWA, transport)
    fused = controller()
    assert fused.layout.num_stamps == 0 and fused.sensor_time.size == 0
    fused.warm_up()
    link = LcmLink(robot, transport, LcmChannels(), fused, wait_timeout=1.0)

    def pump():
        while transport.handle(0.0):
            pass

    bridge.step()
    pump()
    link.connect(fused)
    loop = ControlLoop(fused, link, reference, duration=1.0)
    for k in range(ticks):
        if k:
            bridge.step()
        assert loop.step(0.0)
        pump()
    q_cmd = loop.signals()["q_cmd"]
    np.testing.assert_allclose(q_cmd, [c for c, _ in direct], rtol=0, atol=1e-12)
    # Not a trivial run: the estimator saw the arm's weight, in both shells alike.
    np.testing.assert_allclose(fused.estimator.tau, direct[-1][1], rtol=0, atol=1e-12)
    assert np.abs(direct[-1][1]).max() > 1.0
