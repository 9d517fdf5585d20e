"""`hrp2-drake control`: torque control of a robot over LCM or on its Dynamixel bus
(`tools/control.py`)."""

import argparse

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "control",
        run,
        "torque control of a robot over LCM (the robot's bridge or sim-robot: one tick "
        "per encoder message) or on its Dynamixel bus (a serial port, or sim-servo's: "
        "one sync read, one tick, one sync write per period), with per-tick timing",
        robot=True,
        lcm={
            "required": False,
            "default": "",
            "help": "the robot over LCM: its URL (see sim-robot --lcm)",
        },
        port={"default": ""},
        lockstep=True,
        motor_model={"required": True, "help": "MotorModel YAML"},
        config="ControlConfig YAML file",
        duration="seconds (default 5)",
        motion={
            "choices": ("sinusoid", "hold", "balance"),
            "help": "default: sinusoid; balance: a robot standing on its soles "
            "(sim-robot --scenario standing), its CoM on the authors' sinusoid",
        },
        stiffness={
            "type": _stiffness,
            "help": "the joint stiffness to hold the reference with, N·m/rad: one "
            "value, or one per torque-controlled joint comma-separated (e.g. 1 or "
            "1,2,2,0.5,0.5,0.5); torque_control.controller.stiffness, instead of K6",
        },
        out=True,
    ).set_defaults(scenario=None)


def _stiffness(text: str) -> list[float]:
    """--stiffness: comma-separated numbers (N·m/rad; checked by the config)."""
    try:
        return [float(value) for value in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected numbers in N·m/rad, comma-separated, got '{text}'"
        ) from None


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.tools.control import ControlConfig, run_control, run_ending

    config, sources = options.read_config_on_robot(ControlConfig, args, "robot")
    if args.robot:
        config.robot = args.robot
    options.set_given(config, args, "duration", "motion")
    if args.stiffness is not None:
        config.torque_control.controller.stiffness = args.stiffness
    if bool(args.lcm) == bool(args.port):
        raise ValueError("give the robot's link: --lcm URL or --port DEV (one of them)")
    if args.lockstep and not args.port:
        raise ValueError(
            "--lockstep: only with --port (a lock-step robot behind a bus)"
        )
    out = options.validated_out(config, args)
    summary = run_control(
        config,
        options.motor_model(args, out, config),
        out,
        lcm_url=args.lcm,
        port=args.port,
        lockstep=args.lockstep,
        sources=sources,
    )
    lat = summary["latency_us"]
    print(
        f"report: {out / 'control.md'}; {summary['ticks']} ticks, latency p50 "
        f"{lat['p50']:.0f} µs, p99 {lat['p99']:.0f} µs, {summary['overruns']} over the "
        f"period; torque control {summary['torque_share'] * 100:.1f}% of the run after "
        f"start-up, {len(summary['events'])} fallbacks"
        + (", gave up for good" if summary["gave_up"] else "")
    )
    return options.stopped(run_ending(summary) if summary["fault"] else None)
