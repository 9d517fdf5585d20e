"""The report of a motor identification (paper Sec. 3, 5.2; `hrp2-drake identify`):
the Table 1 analogue, the validation, estimation, parameter, gain and w-sweep tables,
Figures 1 and 3, identification.json and the motor models of every fit.

Written from an `IdentificationResult` (`joint_fits.identify_logs`) alone; the
emulated servo's parameters (ground truth, the simulated robot's) come in as `truth`
for a simulated log, for evaluation only.
"""

import functools
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hrp2_drake.description import RobotDescription, load_robot_description
from hrp2_drake.identification.fitting import overestimation_share
from hrp2_drake.identification.joint_fits import (
    FIT_PURPOSE,
    FITS,
    IdentificationResult,
)
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.report import markdown_table, pyplot, save_figure


def write_report(
    result: IdentificationResult, out: Path, truth: MotorModel | None = None
) -> dict:
    """Writes identification.md, identification.json, motor_model.yaml (the fit of
    `FitConfig.fit`), motor_model_<fit>.yaml for every fit, and the figures;
    returns the results as a dict. `truth`: the emulated servo's motor model of the
    identified joints, for a simulated log (evaluation only); None: a real log."""
    out.mkdir(parents=True, exist_ok=True)
    robot = result.robot
    joints = result.config.identified_joints(robot)
    rows = {}
    for k, r in enumerate(result.joints):
        row = {
            m: {
                "k_tau": float(r.models[m].k_tau[0]),
                "k_v": float(r.models[m].k_v[0]),
                "k_c": float(r.models[m].k_c[0]),
            }
            for m in FITS
        }
        row["validation"] = r.validation
        row["samples"] = r.samples
        row["w_sweep"] = {f"{w:g}": v for w, v in r.w_sweep.items()}
        if r.per_gain:
            row["per_gain"] = {f"{g:g}": v for g, v in r.per_gain.items()}
        if r.joint in robot.published_motor_model:  # [10³ Kτ, 10³ Kv]
            k_tau, k_v = robot.published_motor_model[r.joint]
            row["paper"] = {"k_tau": k_tau * 1e-3, "k_v": k_v * 1e-3}
        if truth is not None:
            row["emulator"] = {
                "k_tau": float(truth.k_tau[k]),
                "k_v": float(truth.k_v[k]),
            }
            row["relative_error_asymmetric"] = {
                p: row["asymmetric"][p] / row["emulator"][p] - 1
                for p in ("k_tau", "k_v")
            }
        rows[r.joint] = row
    summary = {
        "joints": rows,
        "fit": result.config.fit,
        "gain": result.gain,
        "excluded_samples": result.excluded,
    }
    if result.logs:
        summary["logs"] = result.logs
    if result.estimation_rms is not None:
        cols = [robot.joints.index(j) for j in joints]
        summary["torque_estimation"] = {
            j: {
                "rms": float(result.estimation_rms[c]),
                "peak": float(result.estimation_peak[c]),
            }
            for j, c in zip(joints, cols)
        }
    (out / "identification.json").write_text(json.dumps(summary, indent=2))
    result.identified.save(out / "motor_model.yaml")
    for method in FITS:
        MotorModel.from_joints({r.joint: r.models[method] for r in result.joints}).save(
            out / f"motor_model_{method}.yaml"
        )
    figures = plot_figures(result, out)
    (out / "identification.md").write_text(_markdown(result, summary, figures))
    return summary


def _label(joint: str, robot: RobotDescription | None = None) -> str:
    robot = robot or load_robot_description()
    if joint in robot.controlled_joints:
        return robot.labels()[robot.controlled_joints.index(joint)]
    return joint


def _markdown(result: IdentificationResult, summary: dict, figures: list[str]) -> str:
    robot = result.robot
    label = functools.partial(_label, robot=robot)
    joints = summary["joints"]
    lines = _intro(result)
    lines += _logs_table(result)
    lines += _parameter_table(result, joints, label)
    lines += _gain_table(result, joints, label)
    lines += _validation_table(result, joints, label)
    lines += _sweep_table(result, joints, label)
    lines += _estimation_table(summary, label)
    lines += ["", "## Figures", ""] + [f"![{f}]({f})" for f in figures]
    return "\n".join(lines) + "\n"


def _intro(result: IdentificationResult) -> list[str]:
    """The report's title, its samples and what each fit is for."""
    config = result.config
    at_gain = f" at servo gain {result.gain:g}" if result.gain else ""
    return [
        f"# Motor identification of {result.robot.name} (paper Sec. 3, Table 1, "
        "Figures 1 and 3)",
        "",
        f"Samples: {int(result.train.sum())} training, "
        f"{int((~result.train & result.held_out).sum())} held out "
        f"(one {config.held_out_block:g} s block in {config.held_out_every}), window "
        f"{config.window * 1e3:g} ms, w = {config.w:g}. Left out: "
        + ", ".join(f"{n} {what}" for what, n in result.excluded.items())
        + ".",
        "",
        f"`motor_model.yaml` holds the **{config.fit.replace('_', ' ')}** "
        f"fit{at_gain}; every fit is also written as `motor_model_<fit>.yaml`. What "
        "each is for:",
        "",
        *(f"- {m.replace('_', ' ')}: {FIT_PURPOSE[m]}." for m in FITS),
    ]


def _logs_table(result: IdentificationResult) -> list[str]:
    """The logs read (none for a collection): rate, duration, gain, servo on, gaps."""
    if not result.logs:
        return []
    return [
        "",
        "## Logs",
        "",
        *markdown_table(
            [
                "log",
                "raw rate (Hz)",
                "duration (s)",
                "gain",
                "servo on",
                "longest gap (ms)",
            ],
            [
                [
                    r["log"],
                    f"{r['raw_rate_hz']:g}",
                    f"{r['duration_s']:g}",
                    "–" if r["gain"] is None else f"{r['gain']:g}",
                    f"{r['valid_share'] * 100:.0f}%",
                    f"{r['longest_gap_s'] * 1e3:.1f}",
                ]
                for r in result.logs
            ],
        ),
    ]


def _validation_table(result: IdentificationResult, joints: dict, label) -> list[str]:
    """Every fit on the held-out samples, and the piecewise-linear model's notes."""
    lines = [
        "",
        "## Validation on held-out samples",
        "",
        "RMS of Δq̂ − Δq (mrad) / share of samples where |Δq| is over-estimated.",
        "",
    ]
    methods = FITS + ("piecewise_linear",)
    header = [
        "joint",
        *(m.replace("_", " ") for m in methods[:-1]),
        "piecewise-linear (static samples only)",
    ]
    lines += markdown_table(
        header,
        [
            [label(joint)]
            + [
                f"{v['rms'] * 1e3:.3f} / {v['overestimation'] * 100:.1f}%"
                if v
                else "not fitted"
                for v in (row["validation"].get(m) for m in methods)
            ]
            for joint, row in joints.items()
        ],
        align="l" * len(header),
    )
    notes = [
        f"- {label(r.joint)}: {r.piecewise_note}"
        for r in result.joints
        if r.piecewise_note
    ]
    if notes:
        lines += [
            "",
            "The piecewise-linear model (Sec. 3.2, abandoned by the paper; for "
            "comparison only) needs an initial guess of its breakpoints:",
            "",
            *notes,
        ]
    return lines


def _estimation_table(summary: dict, label) -> list[str]:
    """The non-causal torque estimate against the simulated truth (a collection)."""
    if "torque_estimation" not in summary:
        return []
    return [
        "",
        "## Non-causal torque estimate vs ground truth",
        "",
        *markdown_table(
            ["joint", "RMS error (N·m)", "peak |τ| (N·m)", "RMS / peak"],
            [
                [
                    label(j),
                    f"{v['rms']:.3f}",
                    f"{v['peak']:.1f}",
                    f"{v['rms'] / v['peak'] * 100:.2f}%",
                ]
                for j, v in summary["torque_estimation"].items()
            ],
        ),
    ]


def _parameter_table(result, joints: dict, label) -> list[str]:
    """Table 1: every fit's parameters; the emulator's and the paper's columns only
    where there is something to compare."""
    truth = truth_in({"joints": joints})
    paper = any("paper" in row for row in joints.values())
    scale = f" (servo gain {result.gain:g})" if result.gain else ""
    header = ["joint"]
    for m in FITS:
        header += [f"{m.replace('_', ' ')} Kτ", "Kv"] + (
            ["Kc"] if m == "coulomb" else []
        )
    header += ["emulator Kτ", "Kv", "error Kτ, Kv (asym.)"] if truth else []
    header += ["paper Kτ", "Kv"] if paper else []
    rows = []
    for joint, row in joints.items():
        cells = [label(joint)]
        for m in FITS:
            cells += [f"{row[m]['k_tau'] * 1e3:.4f}", f"{row[m]['k_v'] * 1e3:.3f}"]
            cells += [f"{row[m]['k_c'] * 1e3:.3f}"] if m == "coulomb" else []
        if truth:
            e = row.get("relative_error_asymmetric")
            cells += (
                [
                    f"{row['emulator']['k_tau'] * 1e3:.4f}",
                    f"{row['emulator']['k_v'] * 1e3:.3f}",
                    f"{e['k_tau'] * 100:+.1f}%, {e['k_v'] * 100:+.1f}%",
                ]
                if e
                else ["–"] * 3
            )
        if paper:
            p = row.get("paper")
            cells += (
                [f"{p['k_tau'] * 1e3:.3f}", f"{p['k_v'] * 1e3:.3f}"]
                if p
                else ["–", "–"]
            )
        rows.append(cells)
    return [
        "",
        f"## Table 1: identified motor parameters{scale} (10³ Kτ in rad/(N·m), "
        "10³ Kv in s, 10³ Kc in rad)",
        "",
        *markdown_table(header, rows),
    ]


def _gain_table(result, joints: dict, label) -> list[str]:
    """Gain consistency: each fit's Kτ·gain and Kv·gain fitted on each gain's logs
    alone, and their spread (max / min; 1 for a servo whose output is gain · Δq)."""
    if not any("per_gain" in row for row in joints.values()):
        return []
    lines = [
        "",
        "## Gain consistency",
        "",
        "Each fit on the logs of one servo gain at a time: Kτ·gain (rad/(N·m) · gain) "
        "and Kv·gain (s · gain), and their spread (max/min) across the gains. A "
        "P-controlled servo's output is gain · Δq, so a spread of 1 means the model "
        "transfers from one gain to another; the pooled model above assumes it.",
        "",
    ]
    for joint, row in joints.items():
        gains = list(row.get("per_gain", {}))
        if not gains:
            continue
        body = []
        for m in FITS:
            per = [row["per_gain"][g][m] for g in gains]
            cells = [m.replace("_", " ")]
            for p in ("k_tau", "k_v"):
                values = [v[p] for v in per]
                cells += [f"{v:.4g}" for v in values]
                cells.append(
                    f"{max(values) / min(values):.3f}" if min(values) > 0 else "–"
                )
            body.append(cells)
        header = (
            ["fit (" + label(joint) + ")"]
            + [f"Kτ·gain at {g}" for g in gains]
            + ["Kτ spread"]
            + [f"Kv·gain at {g}" for g in gains]
            + ["Kv spread"]
        )
        lines += markdown_table(header, body) + [""]
    return lines[:-1]


def _sweep_table(result, joints: dict, label) -> list[str]:
    config = result.config
    lines = [
        "",
        "## The asymmetric penalty's weight w",
        "",
        "Held-out share of over-estimated |Δq|"
        + (
            " / error of Kτ, Kv against the emulator"
            if truth_in({"joints": joints})
            else ""
        )
        + " (the paper used w = 100).",
        "",
    ]
    rows = []
    for joint, row in joints.items():
        cells = [label(joint)]
        for v in row["w_sweep"].values():
            cell = f"{v['overestimation'] * 100:.1f}%"
            if "emulator" in row:
                e = row["emulator"]
                cell += (
                    f" / {(v['k_tau'] / e['k_tau'] - 1) * 100:+.1f}%, "
                    f"{(v['k_v'] / e['k_v'] - 1) * 100:+.1f}%"
                )
            cells.append(cell)
        rows.append(cells)
    header = ["joint"] + [f"w = {w:g}" for w in config.w_sweep]
    return lines + markdown_table(header, rows, align="l" * len(header))


def truth_in(summary: dict) -> bool:
    return any("emulator" in row for row in summary["joints"].values())


#: The joints of the paper's Figures 1 (knee, hip pitch) and 3 (ankle pitch, hip roll).
FIGURE1_JOINTS = ("RLEG_JOINT3", "RLEG_JOINT2")
FIGURE3_JOINTS = ("RLEG_JOINT4", "RLEG_JOINT1")


def _figure_joints(identified: Sequence[str], paper: Sequence[str]) -> list[str]:
    """The paper's joints of a figure if they were identified, else the robot's first
    two identified joints."""
    return [j for j in paper if j in identified] or list(identified)[:2]


def plot_figures(result: IdentificationResult, out: Path) -> list[str]:
    """Figure 1 (τ vs Δq at near-zero velocity with the fits; HRP-2: knee and hip
    pitch) and Figure 3 (friction part vs q̇, symmetric vs asymmetric; HRP-2: ankle
    pitch and hip roll); another robot: its first two identified joints."""
    by_joint = {r.joint: r for r in result.joints}
    robot = result.robot
    names = []
    for name, paper_joints, plot in (
        ("figure1_torque_vs_delta_q.png", FIGURE1_JOINTS, _plot_figure1),
        ("figure3_friction_fit.png", FIGURE3_JOINTS, _plot_figure3),
    ):
        joints = _figure_joints(by_joint, paper_joints)
        if joints:
            save_figure(plot(result, joints, robot), out / name, tight=True)
            names.append(name)
    return names


def _plot_figure1(
    result: IdentificationResult, joints: list[str], robot: RobotDescription
):
    """Figure 1 of `joints`: τ̂ vs Δq at near-zero velocity, the data and the fits."""
    data, cfg = result.data, result.config
    by_joint = {r.joint: r for r in result.joints}
    column = {name: i for i, name in enumerate(robot.joints)}
    fig, axes = pyplot().subplots(
        1, len(joints), figsize=(6 * len(joints), 4.5), squeeze=False
    )
    for ax, joint in zip(axes[0], joints):
        r, j = by_joint[joint], column[joint]
        static = result.train & (np.abs(data.v[:, j]) < cfg.zero_velocity_threshold)
        tau, v, delta_q = data.joint(j, static)
        ax.scatter(
            tau[v > 0], delta_q[v > 0] * 1e3, s=2, alpha=0.4, label="data, q̇ > 0"
        )
        ax.scatter(
            tau[v < 0], delta_q[v < 0] * 1e3, s=2, alpha=0.4, label="data, q̇ < 0"
        )
        grid = np.linspace(tau.min(), tau.max(), 200)
        for method, style in (("least_squares", "k--"), ("asymmetric", "b-")):
            k = r.models[method].k_tau[0]
            ax.plot(
                grid,
                k * grid * 1e3,
                style,
                label=f"{method.replace('_', ' ')}: Δq = Kτ τ",
            )
        if r.piecewise is not None:
            ax.plot(
                grid, r.piecewise.positive(grid) * 1e3, "g:", label="piecewise, q̇ > 0"
            )
            ax.plot(
                grid, r.piecewise.negative(grid) * 1e3, "m:", label="piecewise, q̇ < 0"
            )
        ax.set_xlabel("τ̂ (N·m)")
        ax.set_ylabel("Δq (mrad)")
        ax.set_title(
            f"{_label(joint, robot)}, |q̇| < {cfg.zero_velocity_threshold} rad/s"
        )
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle("Figure 1: torque vs position error at near-zero velocity")
    return fig


def _plot_figure3(
    result: IdentificationResult, joints: list[str], robot: RobotDescription
):
    """Figure 3 of `joints`: the friction part of the model vs q̇, symmetric (least
    squares) beside asymmetric."""
    data, cfg = result.data, result.config
    by_joint = {r.joint: r for r in result.joints}
    column = {name: i for i, name in enumerate(robot.joints)}
    fig, axes = pyplot().subplots(
        len(joints), 2, figsize=(11, 4 * len(joints)), squeeze=False
    )
    for row, joint in zip(axes, joints):
        r, j = by_joint[joint], column[joint]
        tau, v, delta_q = data.joint(j, result.train)
        for ax, method in zip(row, ("least_squares", "asymmetric")):
            fitted = r.models[method]
            friction = delta_q - fitted.k_tau[0] * tau
            ax.scatter(v, friction * 1e3, s=2, alpha=0.3, color="tab:red", label="data")
            grid = np.linspace(v.min(), v.max(), 100)
            kv = fitted.k_v[0]
            ax.plot(grid, kv * grid * 1e3, "b-", label=f"Kv q̇, Kv = {kv * 1e3:.2f}e-3")
            share = overestimation_share(fitted, tau, v, delta_q)
            kind = (
                "symmetric, eq. 7"
                if method == "least_squares"
                else f"asymmetric, w={cfg.w:g}"
            )
            ax.set_title(
                f"{_label(joint, robot)}, {kind}: over-estimates {share * 100:.1f}%",
                fontsize=10,
            )
            ax.set_xlabel("q̇ (rad/s)")
            ax.set_ylabel("Δq − Kτ τ̂ (mrad)")
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=8)
    fig.suptitle("Figure 3: friction part of the model vs velocity")
    return fig
