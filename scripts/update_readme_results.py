#!/usr/bin/env python3
"""Writes README.md's Results section from a `hrp2-drake reproduce` run.

    hrp2-drake reproduce --out out/reproduce
    python scripts/update_readme_results.py out/reproduce

Replaces the text between the RESULTS markers of README.md with the verdicts, Tables 1-3
and the force metrics of that run, and copies two of its figures to docs/.
"""

import json
import shutil
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BEGIN, END = "<!-- RESULTS:BEGIN -->", "<!-- RESULTS:END -->"
FIGURES = {
    "motion/figure4_tracking_error.png": "docs/figure4_tracking_error.png",
    "force/figure5_force_tracking.png": "docs/figure5_force_tracking.png",
}


def _extract(markdown: str, heading: str) -> list[str]:
    """The table that follows `heading` in a step's report."""
    lines = markdown.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("#") and heading in line)
    table = []
    for line in lines[start + 1 :]:
        if line.startswith("|"):
            table.append(line)
        elif table:
            break
    return table


def results_section(run: Path) -> str:
    from hrp2_drake.paper.motion import paper_sample_count
    from hrp2_drake.paper.claims import verdict_tables

    results = json.loads((run / "results.json").read_text())
    lines = [
        BEGIN,
        "",
        f"From one run of `hrp2-drake reproduce` ({results['total_seconds'] / 60:.1f} min on a",
        "2-core machine). Its `report.md` has every table and figure.",
        "",
    ]
    lines += verdict_tables(results)
    identification = (run / "identify" / "identification.md").read_text()
    motion = (run / "motion" / "motion.md").read_text()
    lines += ["", "**Table 1** (10³ Kτ, 10³ Kv; identified beside the emulator and the paper)", ""]
    lines += _extract(identification, "Table 1")
    lines += [
        "",
        "**Table 2** (average error N⁻¹ sqrt(Σ e²), N = "
        f"{paper_sample_count()['n']:.0f}, rad·10³: simulation (paper, "
        "simulation/paper); position control is what the servo was calibrated to, torque "
        "control is predicted)",
        "",
    ]
    lines += _extract(motion, "Table 2")
    lines += ["", "**Table 3** (maximum error, rad·10³: simulation (paper, simulation/paper))", ""]
    lines += _extract(motion, "Table 3")
    lines += ["", "**K6 = 1 with the estimates where the paper and the authors' code put them** "
              "(maximum error, rad·10³)", ""]
    lines += _extract(motion, "K6 = 1 with the estimates")
    if "## Beyond the paper" in motion:
        lines += ["", "**Beyond the paper: K6 = 0.1 with its future work, tuned, and each part "
                  "alone** (average / maximum error, rad·10³)", ""]
        lines += _extract(motion, "Beyond the paper")
        lines += ["", "**The same, on the climbing motion at another speed (not tuned on)**", ""]
        lines += _extract(motion, "Held out")
        force = (run / "force" / "force.md").read_text()
        lines += ["", "**Force tracking (Fig. 5) with the paper's controller and its variants, "
                  "the motion-tuned one included** (F/T reading; estimate in parentheses)", ""]
        lines += _extract(force, "variants")
    report = (run / "report.md").read_text()
    lines += ["", "**Predictions beside the paper** (Figure 5, Sec. 5.2)", ""]
    lines += _extract(report, "Predictions beside the paper")
    lines += ["", "![Figure 4](docs/figure4_tracking_error.png)", ""]
    lines += ["![Figure 5](docs/figure5_force_tracking.png)", "", END]
    for source, target in FIGURES.items():
        shutil.copyfile(run / source, REPO / target)
    return "\n".join(lines)


def main() -> int:
    if len(sys.argv) != 2:
        print(__doc__, file=sys.stderr)
        return 2
    readme = REPO / "README.md"
    text = readme.read_text()
    if BEGIN not in text or END not in text:
        print("README.md has no RESULTS markers", file=sys.stderr)
        return 1
    (REPO / "docs").mkdir(exist_ok=True)
    before, rest = text.split(BEGIN, 1)
    after = rest.split(END, 1)[1]
    readme.write_text(before + results_section(Path(sys.argv[1])) + after)
    return 0


if __name__ == "__main__":
    sys.exit(main())
