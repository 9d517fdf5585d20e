"""Example: estimate a robot's joint torques online, composing the estimation chain
(paper Sec. 2) with a simulated robot, and compare them with the truth.

    python scripts/example_estimate_torques.py [--robot iiwa14|hrp2|FILE] [--duration 2]

The diagram: the robot's station (its servo holding the home pose against gravity),
then `add_estimator`: Savitzky-Golay filters on the encoders, the IMU (if any) and
the F/T sensors, and the floating-base (or fixed-base) RNEA estimator, which
calibrates the F/T offsets over its first 0.3 s. On a real robot, replace the station
by your robot's diagram with the same port names.
"""

import argparse

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource, VectorLogSink

from hrp2_drake.description import load_robot_description
from hrp2_drake.estimation.estimation_chain import add_estimator
from hrp2_drake.estimation.estimator_config import estimator_config
from hrp2_drake.robot.station import (
    StationConfig,
    initial_joint_positions,
    make_station,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="iiwa14", help="robot description")
    parser.add_argument("--duration", type=float, default=2.0, help="simulated seconds")
    args = parser.parse_args()

    robot = load_robot_description(args.robot)
    station_config = StationConfig(
        robot=args.robot, scenario="fixed_base" if robot.base == "fixed" else "hanging"
    )
    builder = DiagramBuilder()
    station = builder.AddNamedSystem("station", make_station(station_config))
    hold = builder.AddNamedSystem(
        "hold", ConstantVectorSource(initial_joint_positions(station_config))
    )
    builder.Connect(hold.get_output_port(), station.GetInputPort("q_cmd"))
    chain = add_estimator(
        builder,
        station,
        robot.make_plant(),
        estimator_config(robot, window=41, offset_calibration_time=0.3),
    )
    n = len(robot.joints)
    logs = {}
    for name, port in (
        ("tau_hat", chain.estimator.GetOutputPort("tau")),
        ("tau_true", station.GetOutputPort("joint_torque_true")),
    ):
        logs[name] = builder.AddNamedSystem(name, VectorLogSink(n, 0.001))
        builder.Connect(port, logs[name].get_input_port())
    simulator = Simulator(builder.Build())
    simulator.AdvanceTo(args.duration)

    context = simulator.get_context()
    tau_hat, tau_true = (
        logs[k].FindLog(context).data().T for k in ("tau_hat", "tau_true")
    )
    # The estimate describes the robot chain.delay() seconds ago, after the filters
    # filled and the offsets were calibrated (0.5 s).
    lag = round(chain.delay() / 0.001)
    start = 600
    error = tau_hat[start:] - tau_true[start - lag : len(tau_true) - lag]
    rms = np.sqrt(np.mean(error**2, axis=0))
    print(
        f"{robot.name}: τ̂ vs the servo's torque (RMS over {args.duration - 0.6:.1f} "
        "s, N·m)"
    )
    for name, value, peak in zip(robot.joints, rms, np.abs(tau_true).max(axis=0)):
        print(f"  {name:>16}: {value:8.4f}   (|τ| up to {peak:7.2f})")


if __name__ == "__main__":
    main()
