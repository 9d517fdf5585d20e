"""`hrp2-drake record`: a Dynamixel robot's identification logs through its bus
(`tools/record.py`)."""

import argparse

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "record",
        run,
        "record a robot's identification logs through its Dynamixel bus: the "
        "description's excitation through the servos' own position control, one log "
        "per P gain, in the robot's log format (for identify, validate, calibrate)",
        robot=True,
        port={"required": True},
        gain={
            "type": options.number(int, 0),
            "action": "append",
            "default": None,
            "help": "a position P gain to record at (repeat for several; default: the "
            "description's position_loop.gain)",
        },
        lockstep=True,
        config="RecordConfig YAML file",
        out=True,
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.record import RecordConfig, run_record

    config = options.read_config(RecordConfig, args)
    if args.robot:
        config.robot = args.robot
    if args.gain:
        config.gains = list(args.gain)
    out = options.validated_out(config, args)
    summary = run_record(config, args.port, out, lockstep=args.lockstep)
    for log in summary["logs"]:
        print(
            f"  {out / log['log']}: {log['samples']} samples at P gain {log['gain']:g}"
        )
    print(f"report: {out / 'record.md'}")
    faults = [log["fault"] for log in summary["logs"] if log["fault"]]
    return options.stopped(faults[0] if faults else None)
