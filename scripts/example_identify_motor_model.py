"""Example: identify a robot's motor model Δq = Kτ τ + Kv q̇ (paper Sec. 3) from data
collected on its simulated station, composing the library's pieces by hand.

    python scripts/example_identify_motor_model.py [--robot iiwa14|hrp2|FILE]
        [--duration-scale 0.25] [--out out/examples/motor_model.yaml]

Steps: the description's excitation (pushes + increasing sinusoids) run on the station
(`collect`), non-causal estimates of q̇ and τ̂ (`noncausal_estimates`: centred
Savitzky-Golay filters + the torque estimator), then one asymmetric fit per joint
(MathematicalProgram). On a real robot, read its log with `read_robot_log` (this
project's `save_log` format, or the robot's own) and start from `noncausal_estimates`.
"""

import argparse
from pathlib import Path

from hrp2_drake.description import load_robot_description
from hrp2_drake.estimation.estimator_config import estimator_config
from hrp2_drake.estimation.torque_estimator import FloatingBaseTorqueEstimator
from hrp2_drake.identification.dataset import noncausal_estimates
from hrp2_drake.identification.excitation import collect, make_plan
from hrp2_drake.identification.fitting import check_identified, fit_asymmetric
from hrp2_drake.identification.logs import RobotLog
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.robot.station import (
    StationConfig,
    initial_joint_positions,
    make_station,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="iiwa14", help="robot description")
    parser.add_argument("--duration-scale", type=float, default=0.25)
    parser.add_argument(
        "--out",
        type=Path,
        default=Path("out/examples/motor_model.yaml"),
        help="where to write the model (its folder is created)",
    )
    args = parser.parse_args()

    robot = load_robot_description(args.robot)
    config = StationConfig(
        robot=args.robot, scenario="fixed_base" if robot.base == "fixed" else "hanging"
    )
    station = make_station(config)
    plant = station.GetSubsystemByName("plant")
    excitation = robot.identification.scaled(args.duration_scale)
    plan = make_plan(excitation, robot.joints, initial_joint_positions(config))
    push_body = plant.GetBodyByName(excitation.pushes.body).index()
    arrays = collect(station, plan, push_body, excitation.pushes.point)
    log = RobotLog.from_arrays(arrays, robot.joints, robot.joints, source="collected")

    estimator = FloatingBaseTorqueEstimator(robot.make_plant(), estimator_config(robot))
    data = noncausal_estimates(log, estimator, window=81, stride=5)
    fits = {}
    for name in robot.controlled_joints:
        j = robot.joints.index(name)
        moving = data.phase > 0  # pushes and sinusoids, not the moves between them
        tau, v, delta_q = data.joint(j, moving)
        fits[name] = fit_asymmetric(tau, v, delta_q, w=100.0, joint_name=name)
        check_identified(fits[name], tau, v, delta_q, min_explained=None)
        print(
            f"  {name}: Kτ = {fits[name].k_tau[0]:.3e} rad/(N·m), Kv = "
            f"{fits[name].k_v[0]:.4f} s"
        )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    MotorModel.from_joints(fits).save(args.out)
    print(f"motor model: {args.out}")


if __name__ == "__main__":
    main()
