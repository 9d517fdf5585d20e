#!/usr/bin/env python3
"""Writes the results pages from a `hrp2-drake reproduce` run or a `hrp2-drake
balance` run.

    hrp2-drake reproduce --out out/reproduce
    python scripts/update_readme_results.py out/reproduce [--root REPO]
    hrp2-drake balance --robot hrp2 --out out/balance
    python scripts/update_readme_results.py out/balance [--root REPO]

A reproduce run: replaces the text between the RESULTS markers of docs/results.md with
the verdicts, Tables 1-3, the controllers beyond the paper and the force metrics of that
run, and the text between the HEADLINE markers of README.md with its one result table
(the paper's claims, judged) and Figure 4; copies the two figures to docs/.

A balance run (a folder with a balance.json): replaces the text between the BALANCE
markers of README.md with the run's table, and between the BALANCE_COM,
BALANCE_ESTIMATION and BALANCE_PUSHES markers of docs/balance.md with its tables
(`hrp2_drake.experiments.balance.report`, the ones its balance.md has); copies its two
figures to docs/.

REPO (default: the repository this script is in) is where README.md and docs/ are
written. A page is written only if every page of the run can be.
"""

import argparse
import json
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
RESULTS = ("<!-- RESULTS:BEGIN -->", "<!-- RESULTS:END -->")
HEADLINE = ("<!-- HEADLINE:BEGIN -->", "<!-- HEADLINE:END -->")
#: The run's figures and where they are copied, relative to the repository.
FIGURES = {
    "motion/figure4_tracking_error.png": "docs/figure4_tracking_error.png",
    "force/figure5_force_tracking.png": "docs/figure5_force_tracking.png",
}
#: A balance run's markers: README's, and docs/balance.md's three.
BALANCE = ("<!-- BALANCE:BEGIN -->", "<!-- BALANCE:END -->")
BALANCE_COM = ("<!-- BALANCE_COM:BEGIN -->", "<!-- BALANCE_COM:END -->")
BALANCE_ESTIMATION = (
    "<!-- BALANCE_ESTIMATION:BEGIN -->",
    "<!-- BALANCE_ESTIMATION:END -->",
)
BALANCE_PUSHES = ("<!-- BALANCE_PUSHES:BEGIN -->", "<!-- BALANCE_PUSHES:END -->")
#: A balance run's figures and where they are copied.
BALANCE_FIGURES = {
    "balance_com_cop.png": "docs/balance_com_cop.png",
    "balance_pushes.png": "docs/balance_pushes.png",
}
#: The run's files this script reads (and the figures).
INPUTS = (
    "results.json",
    "report.md",
    "identify/identification.md",
    "motion/motion.md",
    "force/force.md",
    *FIGURES,
)


class UpdateError(Exception):
    """A run or a page this script cannot use: its message is one line."""


def _extract(markdown: str, heading: str, source: str) -> list[str]:
    """The table that follows `heading` in a step's report `source`."""
    lines = markdown.splitlines()
    start = next(
        (i for i, line in enumerate(lines) if line.startswith("#") and heading in line),
        None,
    )
    if start is None:
        raise UpdateError(f"{source}: no heading with '{heading}'")
    table = []
    for line in lines[start + 1 :]:
        if line.startswith("|"):
            table.append(line)
        elif table:
            break
    if not table:
        raise UpdateError(f"{source}: no table after the heading '{heading}'")
    return table


def _results(run: Path) -> dict:
    """The run's results.json, with the run's duration in it."""
    path = run / "results.json"
    try:
        results = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise UpdateError(f"{path}: not JSON ({error})") from None
    if not isinstance(results, dict) or "total_seconds" not in results:
        raise UpdateError(f"{path}: no 'total_seconds' (not a finished reproduce run)")
    return results


def _run_line(results: dict) -> str:
    return (
        f"From one run of `hrp2-drake reproduce` ({results['total_seconds'] / 60:.1f} "
        "min on a"
    )


def results_section(run: Path) -> list[str]:
    """docs/results.md's text between its markers (the markers excluded)."""
    from hrp2_drake.paper.claims import verdict_tables
    from hrp2_drake.paper.motion import paper_sample_count

    results = _results(run)
    lines = [
        "",
        _run_line(results),
        "2-core machine). Its `report.md` has every table and figure.",
        "",
    ]
    lines += verdict_tables(results)

    def table(name: str, heading: str) -> list[str]:
        return _extract((run / name).read_text(), heading, str(run / name))

    lines += [
        "",
        "**Table 1** (10³ Kτ, 10³ Kv; identified beside the emulator and the paper)",
        "",
    ]
    lines += table("identify/identification.md", "Table 1")
    lines += [
        "",
        "**Table 2** (average error N⁻¹ sqrt(Σ e²), N = "
        f"{paper_sample_count()['n']:.0f}, rad·10³: simulation (paper, "
        "simulation/paper); position control is what the servo was calibrated to, "
        "torque control is predicted)",
        "",
    ]
    lines += table("motion/motion.md", "Table 2")
    lines += [
        "",
        "**Table 3** (maximum error, rad·10³: simulation (paper, simulation/paper))",
        "",
    ]
    lines += table("motion/motion.md", "Table 3")
    lines += [
        "",
        "**K6 = 1 with the estimates where the paper and the authors' code put them** "
        "(maximum error, rad·10³)",
        "",
    ]
    lines += table("motion/motion.md", "K6 = 1 with the estimates")
    if "## Beyond the paper" in (run / "motion" / "motion.md").read_text():
        lines += [
            "",
            "**Beyond the paper: K6 = 0.1 with its future work, tuned, and each part "
            "alone** (average / maximum error, rad·10³)",
            "",
        ]
        lines += table("motion/motion.md", "Beyond the paper")
        lines += [
            "",
            "**The same, on the climbing motion at another speed (not tuned on)**",
            "",
        ]
        lines += table("motion/motion.md", "Held out")
        lines += [
            "",
            "**Force tracking (Fig. 5) with the paper's controller and its variants, "
            "the motion-tuned one included** (F/T reading; estimate in parentheses)",
            "",
        ]
        lines += table("force/force.md", "variants")
    lines += ["", "**Predictions beside the paper** (Figure 5, Sec. 5.2)", ""]
    lines += table("report.md", "Predictions beside the paper")
    lines += ["", "![Figure 4](figure4_tracking_error.png)", ""]
    lines += ["![Figure 5](figure5_force_tracking.png)", ""]
    return lines


def headline_section(run: Path) -> list[str]:
    """README.md's text between its markers: the paper's claims judged, and Figure 4."""
    from hrp2_drake.paper.claims import verdicts
    from hrp2_drake.report import markdown_table

    results = _results(run)
    rows = [
        [row.claim, row.verdict, row.evidence]
        for row in verdicts(results)
        if row.kind == "paper"
    ]
    lines = [
        "",
        _run_line(results),
        "2-core machine; each row's threshold, this project's own goals and every "
        "table in [docs/results.md](docs/results.md)):",
        "",
    ]
    lines += markdown_table(
        ["claim of the paper, as written (where)", "verdict", "evidence"], rows, "lll"
    )
    lines += [
        "",
        "![Figure 4: position control vs torque control]"
        "(docs/figure4_tracking_error.png)",
        "",
    ]
    return lines


def replace_between(
    text: str, markers: tuple[str, str], lines: list[str], name: str
) -> str:
    """`text` with what lies between its two `markers` replaced by `lines`."""
    begin, end = markers
    once = text.count(begin) == 1 and text.count(end) == 1
    if not once or text.index(begin) > text.index(end):
        raise UpdateError(f"{name}: needs one '{begin}' and, after it, one '{end}'")
    before, rest = text.split(begin, 1)
    after = rest.split(end, 1)[1]
    return before + "\n".join([begin, *lines, end]) + after


def _balance_summary(run: Path) -> dict:
    """The run's balance.json, checked for every key the tables read."""
    from hrp2_drake.experiments.balance.report import SummaryError, check_summary

    path = run / "balance.json"
    try:
        return check_summary(json.loads(path.read_text()), str(path))
    except json.JSONDecodeError as error:
        raise UpdateError(f"{path}: not JSON ({error})") from None
    except SummaryError as error:
        raise UpdateError(str(error)) from None


def balance_sections(run: Path) -> dict[str, list[tuple[tuple[str, str], list[str]]]]:
    """README.md's and docs/balance.md's texts between their markers, by page."""
    from hrp2_drake.experiments.balance import report

    summary = _balance_summary(run)
    source = report.run_line(summary)
    readme = ["", source, "", *report.headline_table(summary), ""]
    com = ["", source, "", *report.com_table(summary), ""]
    estimation = report.estimation_table(summary)
    if estimation:
        met, judged = report.estimation_met(summary)
        goal = summary["settings"]["estimation_goal"]
        estimation = [
            "",
            f"RMS of τ̂ − τ per leg joint against {goal * 100:g}% of its peak |τ| "
            f"(bold: within; {len(met)} of {judged} against τ(t − t_d)). "
            f"{report.estimation_text(summary)}",
            "",
            *estimation,
            "",
        ]
    else:
        estimation = ["", "(This run has no estimation.)", ""]
    pushes = ["", *report.push_table(summary), ""]
    comparison = report.comparison_table(summary)
    if comparison:
        pushes += ["At the largest push both controls survived:", "", *comparison, ""]
    return {
        "README.md": [(BALANCE, readme)],
        "docs/balance.md": [
            (BALANCE_COM, com),
            (BALANCE_ESTIMATION, estimation),
            (BALANCE_PUSHES, pushes),
        ],
    }


def _write(
    root: Path, run: Path, sections: dict, figures: dict[str, str]
) -> list[Path]:
    """Every page's sections replaced, checked before any is written; then the
    figures copied. Returns the files written."""
    texts = {}
    for name, replacements in sections.items():
        page = root / name
        if not page.is_file():
            raise UpdateError(f"{page}: no such page")
        text = page.read_text()
        for markers, lines in replacements:
            text = replace_between(text, markers, lines, str(page))
        texts[page] = text
    for page, text in texts.items():
        page.write_text(text)
    for source, target in figures.items():
        shutil.copyfile(run / source, root / target)
    return [*texts, *(root / target for target in figures.values())]


def update(run: Path, root: Path) -> list[Path]:
    """Writes the pages of the run in `run` under `root` (a balance run's if it has
    a balance.json, else a reproduce run's: docs/results.md and README.md), and
    copies its figures; returns the files written."""
    if (run / "balance.json").is_file():
        missing = [name for name in BALANCE_FIGURES if not (run / name).is_file()]
        if missing:
            raise UpdateError(f"{run}: a balance run without {', '.join(missing)}")
        return _write(root, run, balance_sections(run), BALANCE_FIGURES)
    missing = [name for name in INPUTS if not (run / name).is_file()]
    if missing:
        raise UpdateError(f"{run}: not a reproduce run: no {', '.join(missing)}")
    sections = {
        "docs/results.md": [(RESULTS, results_section(run))],
        "README.md": [(HEADLINE, headline_section(run))],
    }
    return _write(root, run, sections, FIGURES)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.splitlines()[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument(
        "run", type=Path, help="the output folder of a reproduce or a balance run"
    )
    parser.add_argument(
        "--root",
        type=Path,
        default=REPO,
        help="the repository to write (default: this one)",
    )
    args = parser.parse_args(argv)
    try:
        written = update(args.run, args.root)
    except UpdateError as error:
        print(f"update_readme_results: error: {error}", file=sys.stderr)
        return 2
    for path in written:
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
