#!/usr/bin/env python3
"""The bus loop's rate and jitter through the emulated servos: 1, 6 and 12 XL330s at
1, 2 and 4 Mbit/s on a Dynamixel bus, and 1, 6 and 12 STS3215s at 0.5 and 1 Mbit/s
(the STS3215's fastest) on a Feetech bus, each beside the wire-time budget (the
physical limit).

For each bus, `hrp2-drake sim-servo` serves a rack of N XL330 pendulums (one robot, one
plant, IDs 1..N, the twin's servo on each joint) on a pseudo-terminal in real time,
honouring every byte's wire time and the servos' return delay (0 here, as the
description sets it);
the host runs the bus loop's own bus (`hardware.bus_link.ServoBus`: through
dynamixel-sdk or Feetech's scservo_sdk) back to back, without waiting for a clock:
one sync read of [present_velocity, present_position] and one sync write of the goals
per cycle, the goal the measured pose.

Reported per bus: the cycle's p50 and p99 (µs), the achieved rate (1 / p50), and the
budget (`BusTiming.cycle` without adapter latency and compute): what the bytes take on
the wire; the statuses that did not come (a period late enough for the SDK's 34 ms
timeout: the emulator's own hiccups on a shared machine). On a real port, a USB adapter
adds its latency timer to every sync read (an FTDI chip holds received bytes up to it:
1 ms with `setserial low_latency`, 16 ms without), the column `with a USB adapter`.

A Feetech rack is the same pendulums (the XL330's links and twin: the bus, not the
physics, is measured) on an STS3215 bus (Feetech's framing, sign-magnitude values,
P coefficient 32).

    python scripts/bench_bus.py [--cycles 2000] [--kind feetech] [--json out/b.json]
"""

import argparse
import json
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from hrp2_drake.description import load_robot_description, models_root

SERVOS = (1, 6, 12)
BAUDS = (1_000_000, 2_000_000, 4_000_000)
#: The bauds measured per bus kind (the STS3215's fastest is 1 Mbit/s).
KIND_BAUDS = {"dynamixel": BAUDS, "feetech": (500_000, 1_000_000)}
#: An FTDI adapter's latency timer in low-latency mode (s).
USB_LATENCY = 0.001


def _rack(folder: Path, servos: int, baud: int, kind: str = "dynamixel") -> Path:
    """A robot of `servos` XL330 pendulums side by side on one base, one joint each
    (IDs 1..N on one bus at `baud`, no adapter latency: a pseudo-terminal; no compute
    allowance: the host's time is measured), each pendulum and servo the XL330
    pendulum's (its URDF's links, its twin's servo.yaml): its robot.yaml."""
    source = models_root() / "xl330_pendulum"
    target = folder / f"rack_{kind}_{servos}_{baud}"
    target.mkdir(parents=True, exist_ok=True)
    urdf = (source / "xl330_pendulum.urdf").read_text()
    head, _, rest = urdf.partition('<link name="pendulum">')
    pendulum, _, tail = rest.partition("</link>")
    joint = tail[
        tail.index('<joint name="servo"') : tail.index("</transmission>")
        + len("</transmission>")
    ]
    parts = [head]
    for k in range(1, servos + 1):
        parts.append(f'<link name="pendulum{k}">{pendulum}</link>\n')
        parts.append(
            joint.replace('name="servo"', f'name="servo{k}"')
            .replace(
                '<child link="pendulum"/>',
                f'<child link="pendulum{k}"/>\n    <origin xyz="0 {0.1 * k} 0"/>',
            )
            .replace('name="servo_transmission"', f'name="servo{k}_transmission"')
            .replace('name="xl330"', f'name="xl330_{k}"')
            + "\n"
        )
    parts.append("</robot>\n")
    (target / "rack.urdf").write_text("".join(parts))
    description = yaml.safe_load((source / "robot.yaml").read_text())
    names = [f"servo{k}" for k in range(1, servos + 1)]
    description |= {
        "name": f"xl330_rack_{servos}",
        "model_file": "rack.urdf",
        "joints": names,
        "controlled_joints": names,
        "joint_labels": [],
        "initial_positions": [0.0] * servos,
        "identification": {},
        "logs": {"format": "npz"},
        "control_file": "",  # the bus alone: no torque control
    }
    description["bus"] |= {
        "ids": list(range(1, servos + 1)),
        "baud": baud,
        "adapter_latency": 0.0,
        "compute_time": 0.0,
    }
    if kind == "feetech":
        description["bus"] |= {"kind": "feetech", "model": "STS3215"}
        description["position_loop"]["gain"] = 32.0  # a P coefficient (0-254)
    description["sensors"]["period"] = 0.05  # a period the slowest bus here carries
    (target / "robot.yaml").write_text(yaml.safe_dump(description, sort_keys=False))
    twin = yaml.safe_load((source / "servo.yaml").read_text())["joints"]["servo"]
    (target / "servo.yaml").write_text(
        yaml.safe_dump({"joints": {n: twin for n in names}})
    )
    return target / "robot.yaml"


def bench_bus(
    servos: int, baud: int, cycles: int, folder: Path, kind: str = "dynamixel"
) -> dict:
    from hrp2_drake.hardware.bus_link import servo_bus
    from hrp2_drake.hardware.servo_bus import STATUS_OK

    robot_file = _rack(folder, servos, baud, kind)
    emulator = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "hrp2_drake.cli",
            "sim-servo",
            "--robot",
            str(robot_file),
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    try:
        line = emulator.stdout.readline()
        port = line.split(" on ")[1].split()[0]
        robot = load_robot_description(robot_file)
        bus = servo_bus(robot, port)
        q = bus.start()
        cycle = np.zeros(cycles)
        missing = 0
        for k in range(cycles):
            start = time.perf_counter_ns()
            reading = bus.read()
            bus.write(q)
            cycle[k] = (time.perf_counter_ns() - start) * 1e-3
            missing += int(np.count_nonzero(reading.status != STATUS_OK))
        bus.close()
    finally:
        emulator.send_signal(signal.SIGTERM)
        emulator.wait(30)
    timing = robot.bus.timing()
    return {
        "kind": kind,
        "servos": servos,
        "baud": baud,
        "cycles": cycles,
        "p50_us": float(np.percentile(cycle, 50)),
        "p99_us": float(np.percentile(cycle, 99)),
        "rate_hz": float(1e6 / np.percentile(cycle, 50)),
        "budget_us": timing.cycle * 1e6,
        "budget_rate_hz": 1.0 / timing.cycle,
        "with_usb_rate_hz": 1.0 / (timing.cycle + USB_LATENCY),
        "missing_statuses": missing,
    }


def bus_grid(kind: str) -> list[tuple[int, int]]:
    """(servos, baud) of each bus measured on a `kind` bus."""
    return [(n, baud) for n in SERVOS for baud in KIND_BAUDS[kind]]


def print_rows(rows: list[dict]) -> None:
    print(
        "| bus | servos | Mbit/s | cycle p50 (µs) | p99 (µs) | achieved (Hz) | wire "
        "budget (µs) | budget rate (Hz) | with a USB adapter (Hz) | statuses missing |"
    )
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        print(
            f"| {r['kind']} | {r['servos']} | {r['baud'] / 1e6:g} | "
            f"{r['p50_us']:.0f} | "
            f"{r['p99_us']:.0f} | {r['rate_hz']:.0f} | {r['budget_us']:.0f} | "
            f"{r['budget_rate_hz']:.0f} | {r['with_usb_rate_hz']:.0f} | "
            f"{r['missing_statuses']} |"
        )


def main(argv=None) -> list[dict]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=2000)
    parser.add_argument(
        "--kind", action="append", choices=sorted(KIND_BAUDS), help="default: both"
    )
    parser.add_argument("--json", default="")
    args = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        for kind in args.kind or list(KIND_BAUDS):
            for servos, baud in bus_grid(kind):
                rows.append(bench_bus(servos, baud, args.cycles, Path(folder), kind))
                r = rows[-1]
                print(
                    f"bus: {kind}, {servos} servo(s) at {baud / 1e6:g} Mbit/s: p50 "
                    f"{r['p50_us']:.0f} µs, p99 {r['p99_us']:.0f} µs (budget "
                    f"{r['budget_us']:.0f} µs)",
                    file=sys.stderr,
                )
    print_rows(rows)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return rows


if __name__ == "__main__":
    main()
