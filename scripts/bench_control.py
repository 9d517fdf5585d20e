"""Per-tick cost of the controller stack (InverseDynamicsController +
DeltaQTorqueController updates, right leg) and the real-time factor of the
motion experiment's diagrams (position control vs the whole torque-control stack).

Run: .venv/bin/python scripts/bench_control.py
"""

import sys
import time

import numpy as np
from pydrake.systems.analysis import Simulator

from hrp2_drake.assembly.builders import (
    build_position_control,
    build_torque_control,
    simulated_station,
)
from hrp2_drake.assembly.torque_control import TorqueControlConfig
from hrp2_drake.control.inverse_dynamics import (
    InverseDynamicsConfig,
    InverseDynamicsController,
    make_fixed_base_plant,
)
from hrp2_drake.control.safety import (
    SafetyConfig,
    SafetySupervisor,
    supervisor_sensors,
    with_sensor_ranges,
)
from hrp2_drake.control.torque_controller import (
    DeltaQTorqueController,
    TorqueControllerConfig,
)
from hrp2_drake.description import load_robot_description
from hrp2_drake.paper import hrp2
from hrp2_drake.paper.motion import MotionConfig, motion_reference

PERIOD = 1e-3


def _us_per_update(system, context, ticks: int) -> float:
    start = time.perf_counter()
    for tick in range(ticks):
        context.SetTime(tick * PERIOD)
        context.SetDiscreteState(system.EvalUniquePeriodicDiscreteUpdate(context))
    return (time.perf_counter() - start) / ticks * 1e6


def bench_controller_stack(ticks: int = 2000) -> list[dict]:
    joints = list(hrp2.RIGHT_LEG)
    n = len(joints)
    q = hrp2.half_sitting()[:n]
    robot = load_robot_description()
    period = robot.sensors.period
    inverse_dynamics = InverseDynamicsController(
        make_fixed_base_plant(hrp2.add_hrp2, hrp2.BASE_BODY),
        InverseDynamicsConfig(joints=joints, ks=[3000.0], kd=[50.0], period=period),
    )
    context = inverse_dynamics.CreateDefaultContext()
    for name, value in (
        ("q_ref", q),
        ("v_ref", np.full(n, 0.3)),
        ("vdot_ref", np.ones(n)),
        ("q", q + 1e-3),
        ("v", np.full(n, 0.25)),
    ):
        inverse_dynamics.GetInputPort(name).FixValue(context, value)
    id_us = _us_per_update(inverse_dynamics, context, ticks)

    torque = DeltaQTorqueController(
        hrp2.true_motor_model(joints),
        TorqueControllerConfig(joints=joints, period=period),
    )
    context = torque.CreateDefaultContext()
    for name, value in (
        ("tau_desired", np.full(n, 10.0)),
        ("tau_estimated", np.full(n, 9.0)),
        ("v", np.full(n, 0.2)),
        ("q_measured", q),
    ):
        torque.GetInputPort(name).FixValue(context, value)
    dq_us = _us_per_update(torque, context, ticks)

    # The safety supervisor of the 30 joints with HRP-2's sensors (stamps included):
    # its update, and its q_cmd output (computed from live inputs every period).
    sensors = supervisor_sensors(list(hrp2.FT_SENSORS))
    config = with_sensor_ranges(
        SafetyConfig(start_time=0.0), sensors, robot.sensor_ranges
    )
    supervisor = SafetySupervisor(
        hrp2.NUM_JOINTS, sensors, config, period, num_sensor_stamps=7
    )
    context = supervisor.CreateDefaultContext()
    rng = np.random.default_rng(0)
    q30 = hrp2.half_sitting()
    for name, value in (
        ("q_torque", q30 + 1e-3),
        ("q_position", q30),
        ("q_measured", q30),
    ):
        supervisor.GetInputPort(name).FixValue(context, value)
    sizes = {name: 6 if kind == "wrench" else 3 for name, kind in sensors.items()}
    supervisor.GetInputPort("sensor_time").FixValue(context, np.zeros(7))
    for name, size in sizes.items():
        supervisor.GetInputPort(name).FixValue(context, rng.normal(0, 1, size))
    supervisor.ExecuteInitializationEvents(context)
    elapsed = 0.0
    for tick in range(ticks):
        # Healthy inputs (fresh noisy samples and stamps), set outside the timing.
        context.SetTime(tick * PERIOD)
        supervisor.GetInputPort("sensor_time").FixValue(
            context, np.full(7, (tick - 1) * PERIOD)
        )
        for name, size in sizes.items():
            supervisor.GetInputPort(name).FixValue(context, rng.normal(0, 1, size))
        start = time.perf_counter()
        context.SetDiscreteState(supervisor.EvalUniquePeriodicDiscreteUpdate(context))
        supervisor.GetOutputPort("q_cmd").Eval(context)
        elapsed += time.perf_counter() - start
    assert supervisor.GetOutputPort("fault").Eval(context)[0] == 0, (
        "bench inputs must be healthy"
    )
    sup_us = elapsed / ticks * 1e6
    return [
        {"name": "InverseDynamicsController update (6 joints)", "us_per_tick": id_us},
        {"name": "DeltaQTorqueController update (6 joints)", "us_per_tick": dq_us},
        {"name": "controller stack (both)", "us_per_tick": id_us + dq_us},
        {
            "name": "SafetySupervisor update + q_cmd (30 joints, 6 sensors)",
            "us_per_tick": sup_us,
        },
    ]


def bench_motion_experiment(duration: float = 2.0) -> list[dict]:
    config = MotionConfig(start=3.0, end=3.0 + duration, settle=0.0)
    reference = motion_reference(config)
    rows = []
    robot, station, _ = simulated_station(config.station)
    position = build_position_control(robot, station, reference)
    robot, station, period = simulated_station(config.station)
    torque = build_torque_control(
        robot,
        station,
        reference,
        hrp2.true_motor_model(),
        TorqueControlConfig(),
        control_period=period,
    )
    for label, control in (
        ("motion: position control", position),
        ("motion: torque control (estimation + controllers)", torque),
    ):
        simulator = Simulator(control.diagram)
        simulator.Initialize()
        start = time.perf_counter()
        simulator.AdvanceTo(duration)
        rows.append(
            {
                "name": label,
                "real_time_factor": duration / (time.perf_counter() - start),
            }
        )
    return rows


if __name__ == "__main__":
    for row in bench_controller_stack() + bench_motion_experiment():
        print(row, file=sys.stdout)
