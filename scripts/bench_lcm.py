#!/usr/bin/env python3
"""The controller process's tick times over LCM, in real time: `hrp2-drake sim-robot`
and `hrp2-drake control` in two processes through the tcpq hub on 127.0.0.1 (three
processes on this machine's 2 cores: a harder setting than a controller alone on its
own core).

    python scripts/bench_lcm.py [--robot hrp2] [--duration 60] [--out out/bench_lcm]

Prints the tick time's median, p99 and maximum and the overruns (goal: p99 <= 500 µs
over 60 s), and writes the controller's control.md/json in --out.
"""

import argparse
import json
import socket
import subprocess
import sys
import time
from pathlib import Path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robot", default="hrp2")
    parser.add_argument("--duration", type=float, default=60.0)
    parser.add_argument("--out", default="out/bench_lcm")
    parser.add_argument("--motor-model", help="default: the emulator's effective model")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    from hrp2_drake.description import load_robot_description
    from hrp2_drake.experiments.ground_truth import true_motor_model

    robot = load_robot_description(args.robot)
    model = Path(args.motor_model) if args.motor_model else out / "motor_model.yaml"
    if not args.motor_model:
        # A bench needs a model, not an identification run: the emulator's own.
        true_motor_model(robot).save(model)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    url = f"tcpq://127.0.0.1:{port}"
    cli = [sys.executable, "-m", "hrp2_drake.cli"]
    hub = subprocess.Popen([sys.executable, "-m", "hrp2_drake.hardware.tcpq_hub", "--port", str(port)],
                           stdout=subprocess.PIPE, text=True)
    hub.stdout.readline()
    sim = subprocess.Popen(cli + ["sim-robot", "--robot", args.robot, "--lcm", url],
                           stderr=subprocess.DEVNULL)
    try:
        time.sleep(2.0)
        done = subprocess.run(
            cli + ["control", "--robot", args.robot, "--lcm", url, "--motor-model", str(model),
                   "--duration", str(args.duration), "--out", str(out)],
            capture_output=True, text=True,
        )
        print(done.stdout.strip())
        if done.returncode:
            print(done.stderr[-2000:], file=sys.stderr)
            return done.returncode
    finally:
        sim.terminate()
        hub.terminate()
    summary = json.loads((out / "control.json").read_text())
    t = summary["timing"]
    verdict = "PASS" if t["tick_us"]["p99"] <= 500 else "FAIL"
    print(f"controller ticks over LCM ({args.robot}, {args.duration:g} s): median "
          f"{t['tick_us']['median']:.0f} µs, p99 {t['tick_us']['p99']:.0f} µs, max "
          f"{t['tick_us']['max']:.0f} µs, {t['overruns']} overruns: p99 <= 500 µs {verdict}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
