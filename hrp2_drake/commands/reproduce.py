"""`hrp2-drake reproduce`: the identification and every experiment of the paper
(`paper/reproduce.py`)."""

import argparse

from hrp2_drake.commands import options
from hrp2_drake.config import validate_config


def add(commands: options.Commands) -> None:
    options.add_command(
        commands,
        "reproduce",
        run,
        "identification and every experiment of the paper: DIR/report.md, "
        "DIR/results.json, figures and Meshcat replays",
        out=True,
        jobs={"default": 2, "help": "parallel processes"},
        quick="CI-sized durations",
        no_replays={"action": "store_true", "help": "skip Meshcat replays"},
    )


def run(args: argparse.Namespace) -> int:
    from hrp2_drake.paper.claims import verdicts
    from hrp2_drake.paper.reproduce import ReproduceConfig, run_reproduce

    config = ReproduceConfig(
        jobs=args.jobs, quick=args.quick, replays=not args.no_replays
    )
    validate_config(config)
    results = run_reproduce(config, options.output_folder(args.out))
    for row in verdicts(results):  # the paper's claims, then this project's goals
        kind = "paper" if row.kind == "paper" else "project goal"
        print(
            f"  [{row.verdict}] {kind}: {row.claim} ({row.threshold}): {row.evidence}"
        )
    failed = [
        s for s, r in results.items() if isinstance(r, dict) and r.get("ok") is False
    ]
    return 1 if failed else 0
