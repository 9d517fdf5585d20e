#!/usr/bin/env python3
"""The fused controller's tick on a robot (--robot; default HRP-2), closed loop,
against Drake's own `CalcInverseDynamics` on the full robot in the same run.

HRP-2 hanging (30 joints, the IMU, 4 F/T sensors), the tuned K6 = 0.1 controller of the
right leg (models/hrp2/torque_control_k6_0.1.yaml: per-signal windows, disturbance
observer) with the safety supervisor, following the LCM sinusoid (another robot:
hanging if it floats, its torque-control settings as `control` reads them, the
robot's control file over the defaults); the station is
simulated in the same process (`run_in_process`), and only the tick (`tick` +
`command`) is timed, with the garbage collector frozen and disabled as in the LCM
loop, its kernels compiled first and compiling frozen. Each tick is followed by one
`CalcInverseDynamics` (gravity included) of the full robot (HRP-2: floating, 36
velocities) at the same state: the unit of the ratio; and by the tick's own Drake
calls replayed alone (the estimator's SetPositionsAndVelocities, inverse dynamics and
sensor Jacobians, the inverse dynamics' SetPositionsAndVelocities, gravity and inverse
dynamics, on their own contexts): the floor Python cannot go below, in the same unit.

    python scripts/bench_fused.py [--robot R] [--duration 3]
"""

import argparse
import sys
import time
from dataclasses import replace

import numpy as np

#: The issue's goal for the fused tick, in CalcInverseDynamics units (p50; issue 27).
GOAL_RATIO = 6.0
#: HRP-2's tuned controller (the paper's future work, `hrp2-drake tune`).
TUNED = "torque_control_k6_0.1.yaml"


def drake_calls(controller):
    """The tick's Drake calls alone, replayed on the steps' own plants and contexts
    (their private members: a benchmark's look inside)."""
    estimator, inverse_dynamics = controller.estimator, controller.inverse_dynamics

    def replay():
        model, context = estimator._model, estimator._context
        model.SetPositionsAndVelocities(context, estimator._x)
        model.CalcInverseDynamics(context, estimator._vdot, estimator._no_forces)
        estimator._jacobians()
        model, context = inverse_dynamics._model, inverse_dynamics._context
        model.SetPositionsAndVelocities(context, inverse_dynamics._x)
        if inverse_dynamics._accelerated is None and inverse_dynamics._gravity_only:
            model.CalcForceElementsContribution(context, inverse_dynamics._forces)
        model.CalcInverseDynamics(
            context, inverse_dynamics._vdot_full, inverse_dynamics._forces
        )

    return replay


def tuned_config(station):
    from pydrake.common.yaml import yaml_load_typed

    from hrp2_drake.assembly.torque_control import TorqueControlConfig
    from hrp2_drake.control.safety import SafetyConfig

    config = yaml_load_typed(
        schema=TorqueControlConfig,
        filename=str(station.description().path(TUNED)),
        defaults=TorqueControlConfig(),
    )
    return replace(
        config,
        start_time=0.5,
        supervisor=SafetyConfig(stale_time=0.010, stale_samples=12),
    )


def control_config(robot: str, duration: float):
    """(station, the control's config) of `robot`: HRP-2 hanging with its tuned
    controller (`tuned_config`); another robot hanging if it floats, with its
    torque-control settings as `hrp2-drake control` reads them (`load_on_robot`)."""
    from hrp2_drake.assembly.robot_control import load_on_robot
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.robot.station import StationConfig
    from hrp2_drake.tools.control import ControlConfig

    description = load_robot_description(robot)
    floating = description.base != "fixed"
    station = StationConfig(
        robot=robot, scenario="hanging" if floating else "fixed_base"
    )
    if description.path(TUNED).is_file():
        config = ControlConfig(
            robot=robot, duration=duration, torque_control=tuned_config(station)
        )
    else:
        config, _ = load_on_robot(ControlConfig, description)
        config.robot, config.duration = robot, duration
    station.validate()
    config.validate()
    return station, config


def bench_fused_tick(duration: float = 3.0, robot: str = "hrp2") -> list[dict]:
    from pydrake.multibody.tree import MultibodyForces

    from hrp2_drake import kernels
    from hrp2_drake.assembly.builders import torque_chain_parts
    from hrp2_drake.control.fused import FusedController
    from hrp2_drake.hardware.in_process import run_in_process
    from hrp2_drake.hardware.real_time import garbage_collector_frozen
    from hrp2_drake.robot.ground_truth import true_motor_model
    from hrp2_drake.robot.station import make_station
    from hrp2_drake.tools.control import control_reference

    station, config = control_config(robot, duration)
    robot = station.description()
    reference = control_reference(config)
    controller = FusedController(
        torque_chain_parts(
            robot,
            reference,
            true_motor_model(robot),
            config.torque_control_at_period(),
            period=config.period(),
        )
    )
    warm_up = controller.warm_up()
    make_station(station)  # its servo's and sensors' kernels too, before freezing
    replay = drake_calls(controller)
    plant = robot.make_plant()
    context = plant.CreateDefaultContext()
    forces = MultibodyForces(plant)
    vdot = np.full(plant.num_velocities(), 0.1)
    ticks = int(round(duration / config.period()))
    fused_ns = np.zeros(ticks, dtype=np.int64)
    rnea_ns = np.zeros(ticks, dtype=np.int64)
    drake_ns = np.zeros(ticks, dtype=np.int64)
    active = np.zeros(ticks, dtype=bool)
    counter = {"k": 0}

    def timed(step):
        k = counter["k"]
        start = time.perf_counter_ns()
        step()
        middle = time.perf_counter_ns()
        plant.CalcForceElementsContribution(context, forces)
        plant.CalcInverseDynamics(context, vdot, forces)
        end = time.perf_counter_ns()
        replay()
        drake_ns[k] = time.perf_counter_ns() - end
        fused_ns[k], rnea_ns[k] = middle - start, end - middle
        active[k] = controller.torque_active() >= 1.0
        counter["k"] = k + 1

    with garbage_collector_frozen(), kernels.compile_disabled():
        run_in_process(station, controller, reference, ticks, on_tick=timed)
    fused = fused_ns[active] * 1e-3
    rnea = rnea_ns[active] * 1e-3
    drake = drake_ns[active] * 1e-3
    ratio = float(np.median(fused) / np.median(rnea))
    sensors = (["IMU"] if robot.has_imu() else []) + (
        [f"{len(robot.force_torque_sensors)} F/T"] if robot.force_torque_sensors else []
    )
    controlled = config.torque_control.controlled_joints(robot)
    rows = [
        {
            "name": f"fused tick ({robot.name}, {len(robot.joints)} joints, "
            + ", ".join(sensors + [f"{len(controlled)} torque-controlled"])
            + ")",
            "p50_us": float(np.median(fused)),
            "p99_us": float(np.percentile(fused, 99)),
            "ticks": int(active.sum()),
        },
        {
            "name": f"CalcInverseDynamics, full {robot.name} "
            f"({plant.num_velocities()} velocities, gravity)",
            "p50_us": float(np.median(rnea)),
            "p99_us": float(np.percentile(rnea, 99)),
            "ticks": int(active.sum()),
        },
        {
            "name": "the tick's Drake calls alone (the floor)",
            "p50_us": float(np.median(drake)),
            "p99_us": float(np.percentile(drake, 99)),
            "ratio": float(np.median(drake) / np.median(rnea)),
            "ticks": int(active.sum()),
        },
        {
            "name": f"fused tick / CalcInverseDynamics (p50; goal <= {GOAL_RATIO:g})",
            "ratio": ratio,
            "verdict": "PASS" if ratio <= GOAL_RATIO else "FAIL",
        },
        {
            "name": "kernels compiled or loaded before the first tick (s)",
            "warm_up_s": warm_up,
        },
    ]
    for row in rows:
        print(
            "  "
            + ", ".join(
                f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                for k, v in row.items()
            ),
            file=sys.stderr,
        )
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--robot",
        default="hrp2",
        help="a robot description (a robot.yaml or a name in models/; default: hrp2)",
    )
    parser.add_argument("--duration", type=float, default=3.0, help="simulated s")
    args = parser.parse_args()
    bench_fused_tick(args.duration, args.robot)
    return 0


if __name__ == "__main__":
    sys.exit(main())
