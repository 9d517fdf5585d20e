#!/usr/bin/env python3
"""The fused controller's tick on HRP-2, closed loop, against Drake's own
`CalcInverseDynamics` on the full HRP-2 in the same run.

HRP-2 hanging (30 joints, the IMU, 4 F/T sensors), the tuned K6 = 0.1 controller of the
right leg (models/hrp2/torque_control_k6_0.1.yaml: per-signal windows, disturbance
observer) with the safety supervisor, following the LCM sinusoid; the station is
simulated in the same process (`run_in_process`), and only the tick (`tick` +
`command`) is timed, with the garbage collector frozen and disabled as in the LCM
loop. Each tick is followed by one `CalcInverseDynamics` (gravity included) of the
full floating-base HRP-2 (36 velocities) at the same state: the unit of the ratio.

    python scripts/bench_fused.py [--duration 3]
"""

import argparse
import gc
import sys
import time
from dataclasses import replace

import numpy as np

#: The issue's goal for the fused tick, in CalcInverseDynamics units (p50).
GOAL_RATIO = 5.0


def tuned_config(station):
    from pydrake.common.yaml import yaml_load_typed

    from hrp2_drake.control.safety import SafetyConfig
    from hrp2_drake.assembly.builders import TorqueControlConfig

    config = yaml_load_typed(
        schema=TorqueControlConfig,
        filename=str(station.description().path("torque_control_k6_0.1.yaml")),
        defaults=TorqueControlConfig(),
    )
    return replace(
        config, start_time=0.5, supervisor=SafetyConfig(stale_time=0.010, stale_samples=12)
    )


def bench_fused_tick(duration: float = 3.0) -> list[dict]:
    from pydrake.multibody.tree import MultibodyForces

    from hrp2_drake.control.fused import FusedController
    from hrp2_drake.assembly.builders import torque_chain_parts
    from hrp2_drake.tools.ground_truth import true_motor_model
    from hrp2_drake.tools.control import ControlConfig, control_reference
    from hrp2_drake.hardware.control_loop import run_in_process
    from hrp2_drake.robot.station import StationConfig

    station = StationConfig(scenario="hanging")
    config = ControlConfig(robot=station.robot, duration=duration,
                              torque_control=tuned_config(station))
    robot = station.description()
    reference = control_reference(config)
    controller = FusedController(
        torque_chain_parts(robot, reference, true_motor_model(robot), config.torque_control,
                           period=config.period())
    )
    plant = robot.make_plant()
    context = plant.CreateDefaultContext()
    forces = MultibodyForces(plant)
    vdot = np.full(plant.num_velocities(), 0.1)
    ticks = int(duration / 0.001)
    fused_ns = np.zeros(ticks, dtype=np.int64)
    rnea_ns = np.zeros(ticks, dtype=np.int64)
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
        fused_ns[k], rnea_ns[k] = middle - start, end - middle
        active[k] = controller.torque_active() >= 1.0
        counter["k"] = k + 1

    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        run_in_process(station, controller, reference, ticks, on_tick=timed)
    finally:
        gc.enable()
        gc.unfreeze()
    fused = fused_ns[active] * 1e-3
    rnea = rnea_ns[active] * 1e-3
    ratio = float(np.median(fused) / np.median(rnea))
    rows = [
        {"name": "fused tick (HRP-2, 30 joints, IMU, 4 F/T, right leg, observer, supervisor)",
         "p50_us": float(np.median(fused)), "p99_us": float(np.percentile(fused, 99)),
         "ticks": int(active.sum())},
        {"name": "CalcInverseDynamics, full HRP-2 (36 velocities, gravity)",
         "p50_us": float(np.median(rnea)), "p99_us": float(np.percentile(rnea, 99)),
         "ticks": int(active.sum())},
        {"name": f"fused tick / CalcInverseDynamics (p50; goal <= {GOAL_RATIO:g})",
         "ratio": ratio, "verdict": "PASS" if ratio <= GOAL_RATIO else "FAIL"},
    ]
    for row in rows:
        print("  " + ", ".join(f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
                               for k, v in row.items()), file=sys.stderr)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=3.0, help="simulated s")
    args = parser.parse_args()
    bench_fused_tick(args.duration)
    return 0


if __name__ == "__main__":
    sys.exit(main())
