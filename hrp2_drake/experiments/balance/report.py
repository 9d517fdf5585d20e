"""The report of a balance run (`hrp2-drake balance`), from its summary alone.

`runner.py` (beside it) writes a run's summary into `balance.json` and its report,
`balance.md`, with these; `scripts/update_readme_results.py` writes README's balance
table and docs/balance.md's tables from a run's `balance.json` with the same ones,
so that no measured figure is copied by hand. Nothing here reads a robot or a
config: every number and setting a table shows is in the summary (its `settings`
say what the run was asked).

    summary = json.loads(Path("out/balance/balance.json").read_text())
    check_summary(summary, "balance.json")
    lines = com_table(summary)
"""

import math
from collections.abc import Sequence

from hrp2_drake.report import markdown_table

#: The two controls, in the report's order.
MODES = ("torque", "position")

#: README's row of τ̂ judges the leg joints loaded more than this (N·m) at their
#: peak (issue 35's table: a joint that standing barely loads has a large ratio
#: for a small error).
HEADLINE_MIN_PEAK_NM = 5.0

#: What a summary needs (`check_summary`): its keys and its settings' keys.
SUMMARY_KEYS = ("robot", "controlled_joints", "com_motion", "pushes", "settings")
SETTINGS_KEYS = ("solver", "com_motion", "pushes", "estimation_goal")
#: What a run's estimation needs (runner's `_estimation`): τ̂ against τ(t − t_d),
#: the goal's, and against τ(t).
ESTIMATION_KEYS = ("joints", "delay_s", "delayed", "undelayed", "goal")


class SummaryError(ValueError):
    """A summary these tables cannot use: its message is one line."""


def check_summary(summary: object, source: str) -> dict:
    """`summary` if it is a balance run's summary with every key the tables read;
    SummaryError naming `source` and the first missing key otherwise."""
    if not isinstance(summary, dict):
        raise SummaryError(f"{source}: not a balance summary (a JSON object)")
    missing = [key for key in SUMMARY_KEYS if key not in summary]
    if missing:
        raise SummaryError(
            f"{source}: no '{missing[0]}' (a balance.json from another version: "
            "run hrp2-drake balance again)"
        )
    settings = summary["settings"]
    missing = [key for key in SETTINGS_KEYS if key not in settings]
    if missing:
        raise SummaryError(f"{source}: no 'settings.{missing[0]}'")
    absent = [mode for mode in MODES if mode not in summary["com_motion"]]
    if absent:
        raise SummaryError(f"{source}: no 'com_motion.{absent[0]}'")
    estimation = _estimation(summary)
    missing = [k for k in ESTIMATION_KEYS if estimation and k not in estimation]
    if missing:
        raise SummaryError(
            f"{source}: no 'com_motion.torque.estimation.{missing[0]}' (a "
            "balance.json from before τ̂ was judged against the delayed τ: run "
            "hrp2-drake balance again)"
        )
    return summary


def _mm(value) -> str:
    """A length (m) in mm to 0.1 ("0.0", never "-0.0"); "–" if there is none."""
    if value is None or not math.isfinite(value):
        return "–"
    return f"{round(value * 1e3, 1) + 0.0:.1f}"


def _newton(force: float) -> str:
    """A push (N) to 1 N: the search's resolution is 10 N."""
    return f"{force:.0f}"


def _bold_if(cell: str, best: bool) -> str:
    return f"**{cell}**" if best else cell


def _best(values: Sequence[float | None], larger: bool) -> list[bool]:
    """Which of two values is strictly better (none on a tie or a missing one)."""
    if len(values) != 2 or any(v is None or not math.isfinite(v) for v in values):
        return [False] * len(values)
    a, b = values
    if a == b:
        return [False, False]
    first = a > b if larger else a < b
    return [first, not first]


def _rounded_mm(value: float | None) -> float | None:
    """A length as the tables print it (0.1 mm), so that a bold cell is one that
    reads better."""
    return None if value is None or not math.isfinite(value) else round(value * 1e3, 1)


def sinusoid_text(summary: dict) -> str:
    motion = summary["settings"]["com_motion"]
    amplitude = motion["amplitude_m"] * 100
    return (
        f"±{amplitude:g} cm along {motion['axis']}, {motion['period_s']:g} s period, "
        f"{motion['duration_s']:g} s"
    )


def com_table(summary: dict) -> list[str]:
    """The CoM sinusoid under both controls: CoM errors, the smallest CoP margin,
    the soles' peak normal forces and largest tilt, the time in torque control."""
    com = summary["com_motion"]
    best = {
        key: _best([_rounded_mm(com[m][key]) for m in MODES], larger)
        for key, larger in (
            ("com_rms_error_m", False),
            ("com_max_error_m", False),
            ("cop_margin_min_m", True),
        )
    }
    rows = []
    for k, mode in enumerate(MODES):
        m = com[mode]
        rows.append(
            [
                f"{mode} control",
                *(
                    _bold_if(_mm(m[key]), best[key][k])
                    for key in (
                        "com_rms_error_m",
                        "com_max_error_m",
                        "cop_margin_min_m",
                    )
                ),
                ", ".join(f"{f:.0f}" for f in m["peak_normal_force_N"]),
                f"{m['sole_tilt_max_rad'] * 1e3:.2f}",
                "yes" if m["survived"] else "; ".join(m["failures"]),
                f"{m['torque_share'] * 100:.0f}%" if "torque_share" in m else "–",
            ]
        )
    return markdown_table(
        [
            "control",
            "CoM RMS error (mm)",
            "CoM max error (mm)",
            "smallest CoP margin (mm)",
            "peak normal force per sole (N)",
            "largest sole tilt (mrad)",
            "feet flat, no fallback",
            "time in torque control",
        ],
        rows,
    )


def _estimation(summary: dict) -> dict:
    """The torque control's estimation along the sinusoid (runner's `_estimation`),
    empty if the run has none."""
    return summary["com_motion"]["torque"].get("estimation") or {}


def estimation_text(summary: dict) -> str:
    """Why τ̂ is judged against the delayed truth, with the run's delay: one
    sentence for the pages that show `estimation_table`."""
    delay = _estimation(summary)["delay_s"] * 1e3
    return (
        "τ̂ is judged as the paper defines its estimator (Sec. 2): noncausal, at "
        f"time t it estimates the robot at t − t_d, t_d = {delay:g} ms here (the "
        "estimation delay of the chain's filters), so its error is τ̂(t) − τ(t − "
        "t_d); against τ(t), what the controller acts on, the error includes that "
        "delay."
    )


def estimation_table(summary: dict) -> list[str]:
    """τ̂'s RMS error against each torque-controlled joint's peak |τ| along the
    sinusoid, against τ(t − t_d) (bold: within the goal, which is judged there)
    and against τ(t); empty if the run has no estimation."""
    estimation = _estimation(summary)
    if not estimation:
        return []
    goal = estimation["goal"]
    delayed, undelayed = estimation["delayed"], estimation["undelayed"]
    then = f"τ(t − {estimation['delay_s'] * 1e3:g} ms)"
    return markdown_table(
        [
            "joint",
            "peak \\|τ\\| (N·m)",
            f"RMS error, {then} (N·m)",
            f"RMS / peak, {then}",
            "RMS error, τ(t) (N·m)",
            "RMS / peak, τ(t)",
        ],
        [
            [
                j,
                f"{p:.1f}",
                f"{r:.2f}",
                _bold_if(f"{x * 100:.1f}%", x < goal),
                f"{r_now:.2f}",
                f"{x_now * 100:.1f}%",
            ]
            for j, p, r, x, r_now, x_now in zip(
                estimation["joints"],
                delayed["peak_torque_Nm"],
                delayed["rms_error_Nm"],
                delayed["rms_over_peak"],
                undelayed["rms_error_Nm"],
                undelayed["rms_over_peak"],
            )
        ],
    )


def estimation_met(
    summary: dict, min_peak: float = 0.0, against: str = "delayed"
) -> tuple[list[str], int]:
    """The joints whose τ̂ meets the goal among those whose peak |τ| exceeds
    `min_peak` (N·m), and how many joints that is; `against`: "delayed" (τ(t −
    t_d), the goal's) or "undelayed" (τ(t))."""
    if against not in ("delayed", "undelayed"):
        raise ValueError(
            f"estimation_met: against={against!r}, expected 'delayed' or 'undelayed'"
        )
    estimation = _estimation(summary)
    errors = estimation.get(against, {})
    judged = [
        (j, x)
        for j, x, peak in zip(
            estimation.get("joints", []),
            errors.get("rms_over_peak", []),
            errors.get("peak_torque_Nm", []),
        )
        if peak > min_peak
    ]
    return [j for j, x in judged if x < estimation["goal"]], len(judged)


def _pushes_by(summary: dict) -> dict[tuple[str, str], dict]:
    return {(p["direction"], p["mode"]): p for p in summary["pushes"]}


def push_table(summary: dict) -> list[str]:
    """The largest push each control survived per direction (bold: the larger),
    its impulse, and what failed at the next push."""
    duration = summary["settings"]["pushes"]["duration_s"]
    by = _pushes_by(summary)
    rows = []
    for push in summary["pushes"]:
        other = by.get(
            (push["direction"], "position" if push["mode"] == "torque" else "torque")
        )
        survived = push["largest_survived_N"]
        better = other is not None and survived > other["largest_survived_N"]
        failed = push["smallest_failed_N"]
        why = (
            "; ".join(push["runs"][f"{failed:g}"]["failures"])
            if failed is not None
            else "–"
        )
        rows.append(
            [
                push["direction"],
                f"{push['mode']} control",
                _bold_if(_newton(survived), better),
                _bold_if(f"{survived * duration:.1f}", better),
                "–" if failed is None else _newton(failed),
                why,
            ]
        )
    return markdown_table(
        [
            "direction",
            "control",
            "largest push survived (N)",
            "impulse (N·s)",
            "next push (N)",
            "what failed at the next push",
        ],
        rows,
    )


def comparison_table(summary: dict) -> list[str]:
    """At the largest push both controls survived, per direction: the CoM's
    excursion, the peak normal forces, the smallest CoP margin and the time to
    settle (bold: the smaller excursion, the larger margin, the shorter settling)."""
    settled = summary["settings"]["pushes"]["settled_m"]
    rows = []
    for direction, entry in sorted(summary.get("push_comparison", {}).items()):
        runs = [entry[mode] for mode in MODES]
        excursion = _best([_rounded_mm(r["com_excursion_m"]) for r in runs], False)
        margin = _best([_rounded_mm(r["cop_margin_min_m"]) for r in runs], True)
        settle = _best(
            [
                math.inf if r["settle_time_s"] is None else round(r["settle_time_s"], 2)
                for r in runs
            ],
            False,
        )
        for k, (mode, m) in enumerate(zip(MODES, runs)):
            time = m["settle_time_s"]
            rows.append(
                [
                    direction,
                    _newton(entry["force_N"]),
                    f"{mode} control",
                    _bold_if(_mm(m["com_excursion_m"]), excursion[k]),
                    ", ".join(f"{f:.0f}" for f in m["peak_normal_force_N"]),
                    _bold_if(_mm(m["cop_margin_min_m"]), margin[k]),
                    _bold_if("never" if time is None else f"{time:.2f}", settle[k]),
                ]
            )
    if not rows:
        return []
    return markdown_table(
        [
            "direction",
            "push (N)",
            "control",
            "CoM excursion (mm)",
            "peak normal force per sole (N)",
            "smallest CoP margin (mm)",
            f"settle time to {settled * 1e3:g} mm (s)",
        ],
        rows,
    )


def headline_table(summary: dict) -> list[str]:
    """README's table: the sinusoid's CoM errors and CoP margin, the largest push
    per direction, and τ̂ against its goal, torque against position control (bold:
    the better)."""
    settings = summary["settings"]
    com = summary["com_motion"]
    rms = [_rounded_mm(com[m]["com_rms_error_m"]) for m in MODES]
    best = _best(rms, False)
    rows = [
        [
            f"the authors' CoM sinusoid ({sinusoid_text(summary)}): RMS / max CoM "
            "error",
            *(
                _bold_if(
                    f"{_mm(com[m]['com_rms_error_m'])} / "
                    f"{_mm(com[m]['com_max_error_m'])} mm",
                    best[k],
                )
                for k, m in enumerate(MODES)
            ),
        ]
    ]
    best = _best([_rounded_mm(com[m]["cop_margin_min_m"]) for m in MODES], True)
    rows.append(
        [
            "its smallest CoP margin inside the soles",
            *(
                _bold_if(f"{_mm(com[m]['cop_margin_min_m'])} mm", best[k])
                for k, m in enumerate(MODES)
            ),
        ]
    )
    pushes = settings["pushes"]
    by = _pushes_by(summary)
    for direction in pushes["directions"]:
        if not all((direction, m) in by for m in MODES):
            continue
        forces = [by[(direction, m)]["largest_survived_N"] for m in MODES]
        best = _best(forces, True)
        what = (
            f"largest {direction} push, {pushes['duration_s']:g} s on "
            f"{pushes['body']}, both feet flat"
        )
        rows.append(
            [what, *(_bold_if(f"{_newton(f)} N", b) for f, b in zip(forces, best))]
        )
    rows += _estimation_rows(summary)
    return markdown_table(["experiment", "torque control", "position control"], rows)


def _estimation_rows(summary: dict) -> list[list[str]]:
    """README's row of τ̂ (none if the run has no estimation): the leg joints
    loaded more than HEADLINE_MIN_PEAK_NM within the goal against τ(t − t_d), the
    goal's (the ones that miss it named), and how many against τ(t)."""
    met, judged = estimation_met(summary, HEADLINE_MIN_PEAK_NM)
    if not judged:
        return []
    estimation = _estimation(summary)
    now, _ = estimation_met(summary, HEADLINE_MIN_PEAK_NM, against="undelayed")
    missed = [
        j
        for j, peak in zip(
            estimation["joints"], estimation["delayed"]["peak_torque_Nm"]
        )
        if peak > HEADLINE_MIN_PEAK_NM and j not in met
    ]
    return [
        [
            f"τ̂ in double support: leg joints with peak \\|τ\\| > "
            f"{HEADLINE_MIN_PEAK_NM:g} N·m within {estimation['goal'] * 100:g}% RMS "
            f"/ peak of τ {estimation['delay_s'] * 1e3:g} ms earlier (the "
            "estimate's delay: the paper's definition)",
            f"{len(met)} of {judged}"
            + (f" (not {', '.join(missed)})" if missed else "")
            + f"; against τ(t): {len(now)} of {judged}",
            "–",
        ]
    ]


def run_line(summary: dict) -> str:
    """Which run a page's tables are from."""
    return (
        f"From one run of `hrp2-drake balance --robot {summary['robot']}` (its "
        f"`balance.json`; the QP solved by {summary['settings']['solver']})."
    )


def calibration_lines(summary: dict) -> list[str]:
    """The start-up calibration's paragraph (`experiments.balance.calibration`), if
    the run had one: what it found, and its error against the simulated biases."""
    calibration = summary.get("calibration")
    if not calibration:
        return [
            "The robot started on the ground, its F/T offsets not calibrated.",
            "",
        ]
    errors = calibration["calibration_error"]
    sensors = [e for name, e in errors.items() if name != "imu"]
    torque = max(e["torque_error_Nm"] for e in sensors)
    force = max(e["force_error_N"] for e in sensors)
    imu = errors.get("imu")
    imu_text = (
        f"; the IMU's (the robot standing still: the gyro's mean reading, the "
        f"accelerometer's minus gravity in its frame) within "
        f"{imu['accelerometer_error']:.2g} m/s² and {imu['gyroscope_error']:.2g} rad/s"
        if imu
        else ""
    )
    x, y = (v * 1e3 for v in calibration["com_offset_m"])
    return [
        "Calibrated at start-up as the authors calibrated the real HRP-2: the F/T "
        "offsets found with the robot lifted, its feet free (the filtered reading "
        "plus the model's prediction), then the robot put down and the CoM offset "
        f"taken (the soles' measured CoP minus the model's CoM: {x:.2f}, {y:.2f} "
        "mm). Against the simulated sensors' biases (ground truth), the offsets "
        f"are within {torque:.3g} N·m and {force:.3g} N{imu_text}.",
        "",
    ]


def report_markdown(summary: dict) -> str:
    """A run's `balance.md`."""
    settings = summary["settings"]
    pushes = settings["pushes"]
    lines = [
        f"# Balance of {summary['robot']}: torque against position control",
        "",
        f"Torque control: the whole-body QP with both soles' contacts "
        f"({settings['solver']}), its τ* through the Δq controller of "
        f"{len(summary['controlled_joints'])} leg joints with τ̂ from the paper's "
        "estimator; the other joints in position control. Position control: the "
        "same CoM reference through inverse kinematics, the robot's servo tracking "
        "it. Contact forces, CoP and CoM are ground truth.",
        "",
        *calibration_lines(summary),
        f"## CoM tracking: the authors' sinusoid ({sinusoid_text(summary)})",
        "",
        *com_table(summary),
    ]
    estimation = estimation_table(summary)
    if estimation:
        met, judged = estimation_met(summary)
        lines += [
            "",
            f"Estimation in double support (torque control): RMS of τ̂ − τ per leg "
            f"joint against {settings['estimation_goal'] * 100:g}% of its peak |τ| "
            f"(this project's goal; met on {len(met)} of {judged} against τ(t − "
            f"t_d)). {estimation_text(summary)}",
            "",
            *estimation,
        ]
    lines += [
        "",
        f"## Pushes: {pushes['duration_s']:g} s pulses on {pushes['body']}",
        "",
        f"Failure: a sole slides or lifts {pushes['sole_slip_m'] * 1e3:g} mm or "
        f"tilts {pushes['sole_tilt_rad']:g} rad (its heel or toes lift), the base "
        f"drops {pushes['fall_drop_m'] * 1e3:g} mm, or torque control falls back to "
        f"position control. Forces doubled from {pushes['first_N']:g} N, then "
        f"bisected to {pushes['resolution_N']:g} N.",
        "",
        *push_table(summary),
    ]
    comparison = comparison_table(summary)
    if comparison:
        lines += ["", "At the largest push both controls survived:", "", *comparison]
    lines += [
        "",
        "![CoM and CoP](balance_com_cop.png)",
        "",
        "![Pushes](balance_pushes.png)",
        "",
    ]
    return "\n".join(lines)
