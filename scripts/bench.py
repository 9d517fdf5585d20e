#!/usr/bin/env python3
"""Benchmarks of hrp2_drake, in one run so that ratios between rows are meaningful.

Sections (all by default; pick with --only):
  sim        real-time factor of the simulated HRP-2 per scenario (goal: >= 3x for
             fixed_base, >= 1x for standing, one core), and of the bare plant without
             servo and sensors (baseline: what our Python systems cost on top).
  sg         per-tick cost of the Savitzky-Golay filters (scripts/bench_savitzky_golay.py).
  estimator  per-tick cost of the floating-base torque estimator (scripts/bench_estimator.py).
  control    per-tick cost of the controller stack and real-time factor of the motion
             experiment's diagrams (scripts/bench_control.py).
  fit        fit_asymmetric from 10^3 to 10^6 samples, Newton and QP (scripts/bench_fitting.py).

Figures vary from run to run (2 cores, shared): compare rows of the same run.

    python scripts/bench.py [--only sim,sg] [--duration 3] [--json out/bench.json]
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import ConstantVectorSource

sys.path.insert(0, str(Path(__file__).resolve().parent))

from hrp2_drake.robot import model  # noqa: E402
from hrp2_drake.robot.station import (  # noqa: E402
    StationConfig,
    initial_joint_positions,
    make_station,
)


def _real_time_factor(diagram, duration: float) -> float:
    simulator = Simulator(diagram)
    simulator.Initialize()
    start = time.perf_counter()
    simulator.AdvanceTo(duration)
    return duration / (time.perf_counter() - start)


def bench_simulation(duration: float) -> list[dict]:
    rows = []
    for scenario in ("fixed_base", "hanging", "standing", "standing_on_block"):
        config = StationConfig(scenario=scenario)
        builder = DiagramBuilder()
        station = builder.AddSystem(make_station(config))
        source = builder.AddSystem(ConstantVectorSource(initial_joint_positions(config)))
        builder.Connect(source.get_output_port(), station.GetInputPort("q_cmd"))
        rtf = _real_time_factor(builder.Build(), duration)
        rows.append({"name": f"simulate {scenario}", "real_time_factor": rtf})
        print(f"  simulate {scenario:18s} {rtf:6.2f}x real time", file=sys.stderr)
    # Baseline: the same plant (fixed base), constant actuation, no servo, no sensors.
    from pydrake.multibody.plant import AddMultibodyPlant, MultibodyPlantConfig

    builder = DiagramBuilder()
    plant, _ = AddMultibodyPlant(
        MultibodyPlantConfig(time_step=1e-3, discrete_contact_approximation="sap"), builder
    )
    model.add_hrp2(plant)
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName(model.BASE_BODY))
    plant.Finalize()
    torque = builder.AddSystem(ConstantVectorSource(np.zeros(plant.num_actuators())))
    builder.Connect(torque.get_output_port(), plant.get_actuation_input_port())
    rtf = _real_time_factor(builder.Build(), duration)
    rows.append({"name": "baseline: bare fixed-base plant", "real_time_factor": rtf})
    print(f"  bare fixed-base plant     {rtf:6.2f}x real time", file=sys.stderr)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", default="sim,sg,estimator,control,fit")
    parser.add_argument("--duration", type=float, default=3.0, help="simulated s")
    parser.add_argument("--json", type=Path, help="also write the rows here")
    args = parser.parse_args()
    sections = set(args.only.split(","))

    results: dict[str, list[dict]] = {}
    if "sim" in sections:
        print("simulation", file=sys.stderr)
        results["sim"] = bench_simulation(args.duration)
    if "sg" in sections:
        from bench_savitzky_golay import bench_savitzky_golay

        print("savitzky-golay", file=sys.stderr)
        results["sg"] = bench_savitzky_golay()
    if "estimator" in sections:
        try:
            from bench_estimator import bench_estimator
        except ImportError as error:
            print(f"estimator: skipped ({error})", file=sys.stderr)
        else:
            print("estimator", file=sys.stderr)
            results["estimator"] = bench_estimator()
    if "control" in sections:
        from bench_control import bench_controller_stack, bench_motion_experiment

        print("control", file=sys.stderr)
        results["control"] = bench_controller_stack() + bench_motion_experiment()
    if "fit" in sections:
        from bench_fitting import bench_fitting

        print("fitting", file=sys.stderr)
        results["fit"] = bench_fitting()

    for section, rows in results.items():
        print(f"\n## {section}")
        keys = sorted({k for row in rows for k in row if k != "name"})
        print("| name | " + " | ".join(keys) + " |")
        print("| --- |" + " --- |" * len(keys))
        for row in rows:
            cells = [
                f"{row[k]:.4g}" if isinstance(row.get(k), float) else str(row.get(k, ""))
                for k in keys
            ]
            print(f"| {row['name']} | " + " | ".join(cells) + " |")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
