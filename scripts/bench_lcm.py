#!/usr/bin/env python3
"""The controller process's tick times over LCM, in real time: `hrp2-drake sim-robot`
and `hrp2-drake control` in two processes through the tcpq hub on 127.0.0.1. The
controller is pinned to CPU 0, the simulated robot and the hub to CPU 1 (as a real
controller gets its own core; the robot's side stands for the robot's own computer).

    python scripts/bench_lcm.py [--robot hrp2] [--duration 60] [--out out/bench_lcm]

Prints the tick time's median, p99 and maximum and the overruns (goal: p99 <= 500 µs
over 60 s), and writes the controller's control.md/json in --out.
"""

import argparse
import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path


def bench_lcm(robot_name: str, duration: float, out: Path, motor_model: str = "") -> dict:
    """Runs the hub, `sim-robot` and `control` (pinned: the controller on the first
    CPU, the robot and the hub on the second); returns the controller's tick times."""
    from hrp2_drake.description import load_robot_description
    from hrp2_drake.experiments.ground_truth import true_motor_model

    out.mkdir(parents=True, exist_ok=True)
    robot = load_robot_description(robot_name)
    model = Path(motor_model) if motor_model else out / "motor_model.yaml"
    if not motor_model:
        # A bench needs a model, not an identification run: the emulator's own.
        true_motor_model(robot).save(model)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"tcpq://127.0.0.1:{port}"
    cli = [sys.executable, "-m", "hrp2_drake.cli"]
    cpus = sorted(os.sched_getaffinity(0))
    controller_cpu, robot_cpu = ({cpus[0]}, {cpus[1]}) if len(cpus) > 1 else (None, None)

    def pinned(cpu):
        return None if cpu is None else (lambda: os.sched_setaffinity(0, cpu))

    hub = subprocess.Popen([sys.executable, "-m", "hrp2_drake.hardware.tcpq_hub", "--port", str(port)],
                           stdout=subprocess.PIPE, text=True, preexec_fn=pinned(robot_cpu))
    hub.stdout.readline()
    sim = subprocess.Popen(cli + ["sim-robot", "--robot", robot_name, "--lcm", url],
                           stderr=subprocess.DEVNULL, preexec_fn=pinned(robot_cpu))
    try:
        time.sleep(2.0)
        done = subprocess.run(
            cli + ["control", "--robot", robot_name, "--lcm", url, "--motor-model", str(model),
                   "--duration", str(duration), "--out", str(out)],
            capture_output=True, text=True, preexec_fn=pinned(controller_cpu),
        )
        if done.returncode:
            raise RuntimeError(done.stderr[-2000:])
    finally:
        sim.terminate()
        hub.terminate()
    t = json.loads((out / "control.json").read_text())["timing"]
    row = {
        "name": f"controller over LCM, {robot_name}, {duration:g} s",
        "median_us": t["tick_us"]["median"],
        "p99_us": t["tick_us"]["p99"],
        "max_us": t["tick_us"]["max"],
        "overruns": t["overruns"],
        "p99_goal_500us": "PASS" if t["tick_us"]["p99"] <= 500 else "FAIL",
    }
    print(f"  {row['name']}: median {row['median_us']:.0f} µs, p99 {row['p99_us']:.0f} µs, max "
          f"{row['max_us']:.0f} µs, {row['overruns']} overruns: p99 <= 500 µs "
          f"{row['p99_goal_500us']}", file=sys.stderr)
    return row


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="hrp2")
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--out", default="out/bench_lcm")
    parser.add_argument("--motor-model", default="", help="default: the emulator's effective model")
    args = parser.parse_args()
    bench_lcm(args.robot, args.duration, Path(args.out), args.motor_model)
    return 0


if __name__ == "__main__":
    sys.exit(main())
