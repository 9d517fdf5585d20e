"""`hrp2-drake track`: torque control of any robot against its position servo
(`tools/track.py`)."""

import argparse

from hrp2_drake.commands import options


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "track",
        run,
        "torque control of any robot against its position servo: joint tracking, and a "
        "force task at the tool (fixed-base robots)",
        robot=True,
        config="TrackConfig YAML file",
        motor_model=True,
        quick="shorter runs (CI)",
        out=True,
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.assembly.identification import IdentifyConfig
    from hrp2_drake.tools.track import TrackConfig, can_press, run_track

    config, sources = options.read_config_on_robot(TrackConfig, args, "station.robot")
    # --robot R, floating: hanging unless the file says otherwise (the iiwa's default
    # station is fixed_base).
    options.use_robot(config.station, args, floating="hanging" if args.robot else "")
    robot = config.station.description()
    if robot.base == "fixed" and not can_press(robot):
        # Nothing to press with (no tool_frame and force_sensor): unless asked for.
        config.force_task = config.force_task and options.config_sets(
            args, "force_task"
        )
    if args.quick:
        config.duration, config.force_duration, config.k6 = 2.5, 2.0, config.k6[:1]
    out = options.validated_out(config, args)
    identify = IdentifyConfig(
        station=config.station, duration_scale=0.5 if args.quick else 1.0
    )
    summary = run_track(
        config, options.motor_model(args, out, config, identify), out, sources=sources
    )
    print(f"report: {out / 'track.md'}")
    for name, errors in summary["tracking"].items():
        print(f"  {name}: maximum error {max(errors['maximum']) * 1e3:.2f} mrad")
    if "force_task" in summary:
        print(f"  force task: RMS error {summary['force_task']['rms_error_N']:.2f} N")
    return 0
