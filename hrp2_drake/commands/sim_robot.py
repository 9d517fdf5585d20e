"""`hrp2-drake sim-robot`: the simulated robot behind the LCM channels
(`tools/control.py`)."""

import argparse

from hrp2_drake.commands import options
from hrp2_drake.config import validate_config


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "sim-robot",
        run,
        "the simulated robot behind the LCM channels, in real time: what a real "
        "robot's bridge must do",
        robot=True,
        lcm=True,
        scenario="default: hanging (fixed robots: fixed_base)",
        duration={
            "default": float("inf"),
            "help": "seconds (default: until Ctrl-C or SIGTERM)",
        },
        realtime_rate={
            "type": options.number(float, 0.0),
            "default": 1.0,
            "help": "target real-time rate (default 1; < 1 slows the robot's clock, "
            "for tests)",
        },
        lockstep={
            "action": "store_true",
            "help": "advance a period only once the "
            "controller's command for the last one has come (after the first "
            "command: or 0.2 s without one): a clock independent of the machine, "
            "for tests",
        },
        out={
            "default": None,
            "help": "write the ground truth (sim_robot.npz) here on exit",
        },
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.robot.station import StationConfig
    from hrp2_drake.tools.control import run_sim_robot

    station = StationConfig()
    options.use_robot(station, args)
    validate_config(station)
    out = options.output_folder(args.out) if args.out else None
    summary = run_sim_robot(
        station,
        args.lcm,
        args.duration,
        out,
        rate=args.realtime_rate,
        lockstep=args.lockstep,
    )
    print(
        f"sim-robot: {summary['simulated']:.2f} s simulated; command watchdog tripped "
        f"{summary['watchdog_trips']} times"
        + (", holding the measured pose at the end" if summary["holding"] else "")
    )
    return options.stopped(
        f"{summary['fault']}; held the measured pose" if summary["fault"] else None
    )
