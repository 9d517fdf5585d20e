"""`hrp2-drake simulate`: a scenario with the position servo holding its pose or
following a trajectory; the logged signals (`tools/simulate.py`)."""

import argparse
import dataclasses

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "simulate",
        run,
        "run a scenario with the position servo holding half-sitting or following a "
        "trajectory; write the logged signals (.npz)",
        robot=True,
        config="SimulateConfig YAML file",
        scenario="default: standing (a fixed robot: fixed_base)",
        duration="simulated seconds (default 5)",
        trajectory="'default' (the robot's own, HRP-2: stair climbing) or a file: time "
        "+ the joint angles",
        seed={
            "type": options.number(int, 0, strict=False),
            "help": "sensor noise seed",
        },
        out={"default": "out", "help": "output folder (default: out)"},
        html={"action": "store_true", "help": "write a Meshcat HTML replay"},
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.simulate import (
        SimulateConfig,
        run_simulate,
        write_simulation,
    )

    config = options.read_config(SimulateConfig, args)
    options.use_robot(config.station, args)
    options.set_given(config, args, "duration", "trajectory")
    if args.seed is not None:
        config.station.sensors = dataclasses.replace(
            config.station.sensors_config(), seed=args.seed
        )
    out = options.validated_out(config, args)

    result = run_simulate(config, html=args.html)
    files, summary = write_simulation(result, config, out)
    print(f"log: {files['log']} ({len(result.signals['t'])} samples)")
    if "replay" in files:
        print(f"replay: {files['replay']}")
    for key, value in summary.items():
        print(f"  {key}: {value:.6g}")
    return 0
