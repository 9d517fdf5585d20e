"""`hrp2-drake sim-servo`: the simulated robot's servos (Dynamixel or Feetech, as its
bus says) on a pseudo-terminal (`hardware/sim_servo.py`)."""

import argparse

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "sim-servo",
        run,
        "the simulated robot's servos on a pseudo-terminal (Dynamixel Protocol 2.0 "
        "or Feetech's, as the robot's bus says; the robot's physics behind every ID, "
        "wire time and return delays honoured): prints the port's path",
        robot=True,
        lockstep={
            "action": "store_true",
            "help": "the robot's clock is the bus traffic "
            "(one period per sync read): deterministic, for tests",
        },
        realtime_rate={
            "type": options.number(float, 0.0),
            "default": 1.0,
            "help": "target real-time rate (default 1)",
        },
        duration={
            "default": float("inf"),
            "help": "seconds (default: until Ctrl-C or SIGTERM)",
        },
        fault={
            "action": "append",
            "help": "inject a fault, e.g. silent:1@2.0, crc:1@1.5x20, "
            "hardware:1@2.0:overload, close@3.0, wrong_model:1:XM430-W350, "
            "push:1@2.0:0.1 (0.1 N m on servo 1's joint from 2 s on: a hand's push), "
            "push-force:gripper_frame_link@2.0:0,0,-1 (1 N down, world frame, on that "
            "body of the model from 2 s on; 0,0,0 lets go) (repeat for several)",
        },
        ids={
            "default": "",
            "help": "serve these IDs instead of the description's "
            "(comma-separated), e.g. to test a wrong ID",
        },
        out={
            "default": None,
            "help": "write a report (sim_servo.md, sim_servo.json) here on exit",
        },
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.hardware.sim_servo import parse_fault, run_sim_servo

    faults = [parse_fault(spec) for spec in args.fault or []]
    ids = [int(x) for x in args.ids.split(",")] if args.ids else None
    out = options.output_folder(args.out) if args.out else None
    summary = run_sim_servo(
        args.robot or "",
        lockstep=args.lockstep,
        rate=args.realtime_rate,
        duration=args.duration,
        faults=faults,
        ids=ids,
        out=out,
    )
    stopped = summary.get("stopped", "")
    return options.stopped(stopped if stopped and "closed" in stopped else None)
