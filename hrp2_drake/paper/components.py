"""Analysis of the control components (paper Sec. 5.5, Figure 6).

The torque controller's input Δq splits into six components (Sec. 4.2, eq. 13-14;
`DeltaQTorqueController` outputs each one):

    Δq = K_τ (M_j q̈_d + ĥ_j − J_jᵀ f_d)     feedforward torque
       + K_v q̇                              feedforward friction
       + K6 e_q + K7 ė_q + K8 ë_q + K9 e_f  feedback position, velocity,
                                            acceleration, force

From logged runs (the motion experiment at K6 = 0.1 and K6 = 1, the force
experiment) this module measures how much each component contributes to Δq, for the
paper's six panels: hip pitch and knee in motion control at K6 = 0.1 and 1 (Fig.
6a-d), knee and ankle pitch in force control (Fig. 6e-f), and checks the paper's
conclusions by numbers:

  - motion control: "feedforward friction" contributes most, then "feedback
    position";
  - force control: "feedforward torque" most, then "feedback force" (and "feedback
    position" for the ankle pitch).

"Contribution" is the RMS of the component over the analysed window (rad); its share
is RMS_c / Σ_c RMS_c. The RMS keeps the mean: in force control the feedforward torque
is mostly the static load the foot carries, which is a real part of the command. The
report also gives the standard deviation (the varying part alone) and the ranking by
it, since the paper's Fig. 6 shows time series from which either reading could be
taken; components.json has the mean |·| and the peak as well.

With the builders' default TorqueControlConfig the velocity terms use the reference
velocity q̇_d (see its docstring): "feedback velocity" K7 (q̇_d − q̇_d) is then zero,
and in force control (q̇_d = 0) so is "feedforward friction" K_v q̇_d.

Windows: in motion control, from the time the reference starts moving (q_ref of the
right leg leaves its first value) to the end; in force control, from the time the
force reference f_ref,z starts changing (the sinusoid) to the end; either stops at a
fallback to position control. Both can be given instead.
"""

import json
import math
import re
from pathlib import Path

import numpy as np

from hrp2_drake.control.torque_chain import COMPONENTS
from hrp2_drake.paper import hrp2
from hrp2_drake.paper.claims import PANELS, check_panel
from hrp2_drake.report import legend_beside, markdown_table, pyplot, save_figure

#: The components' labels, the paper's words.
COMPONENT_LABELS = {name: name.replace("_", " ") for name in COMPONENTS}
#: The motion runs of Fig. 6a-d, by K6.
MOTION_K6 = (0.1, 1.0)


def find_motion_run(motion_signals: dict[str, dict], k6: float) -> str:
    """The label of the torque-control run at `k6` among the motion experiment's
    signals (labels as `run_motion` writes them, "torque control K6=0.1"; the
    paper-literal run is skipped)."""
    for label in motion_signals:
        match = re.search(r"K6\s*=\s*([0-9.]+(?:[eE][+-]?[0-9]+)?)", label)
        if match and "," not in label and math.isclose(float(match[1]), k6):
            return label
    raise KeyError(
        f"analyse_components: no motion run with K6 = {k6:g} among "
        f"{list(motion_signals)}"
    )


def _active_until(signals: dict[str, np.ndarray]) -> int:
    """The index of the first fallback sample (len if none)."""
    fallback = signals.get("fallback_active")
    if fallback is None or not np.any(fallback > 0):
        return len(signals["t"])
    return int(np.argmax(fallback[:, 0] > 0))


def motion_window(
    signals: dict[str, np.ndarray], start: float | None = None
) -> np.ndarray:
    """Samples of a motion run to analyse: from `start` (default: when the right
    leg's q_ref starts moving) until a fallback."""
    t = signals["t"]
    if start is None:
        leg = [hrp2.JOINT_NAMES.index(j) for j in hrp2.RIGHT_LEG]
        moved = np.abs(signals["q_ref"][:, leg] - signals["q_ref"][0, leg]).max(axis=1)
        start = t[np.argmax(moved > 1e-6)] if np.any(moved > 1e-6) else t[0]
    window = t >= start
    window[_active_until(signals) :] = False
    return window


def force_window(
    signals: dict[str, np.ndarray], start: float | None = None
) -> np.ndarray:
    """Samples of a force run to analyse: from `start` (default: when f_ref,z starts
    changing, the sinusoid; without "f_ref", when torque control starts) until a
    fallback."""
    t = signals["t"]
    if start is None:
        if "f_ref" in signals:
            fz = signals["f_ref"][:, 5]
            moved = np.abs(fz - fz[0]) > 1e-9
        else:
            moved = np.abs(signals["feedforward_torque"]).max(axis=1) > 0
        start = t[np.argmax(moved)] if np.any(moved) else t[0]
    window = t >= start
    window[_active_until(signals) :] = False
    return window


def component_statistics(
    signals: dict[str, np.ndarray], joint: str, window: np.ndarray
) -> dict:
    """Per component of Δq for one joint over `window`: rms, mean_abs, std, peak
    (rad), share (rms / Σ rms), and the rankings by rms and by std; also the largest
    |Σ components − delta_q| over the window's unsaturated samples (rad), the check
    that the six components add up to the command.

    The component ports are the controller's joint vectors (the right leg, in
    hrp2.RIGHT_LEG order)."""
    k = hrp2.RIGHT_LEG.index(joint)
    values = {name: signals[name][window, k] for name in COMPONENTS}
    stats = {
        name: {
            "rms": float(np.sqrt(np.mean(x**2))),
            "mean_abs": float(np.mean(np.abs(x))),
            "std": float(np.std(x)),
            "peak": float(np.abs(x).max()),
        }
        for name, x in values.items()
    }
    total = sum(s["rms"] for s in stats.values())
    total_std = sum(s["std"] for s in stats.values())
    for s in stats.values():
        s["share"] = s["rms"] / total if total > 0 else 0.0
        s["share_std"] = s["std"] / total_std if total_std > 0 else 0.0
    delta_q = signals["delta_q"][window, k]
    summed = np.sum([values[name] for name in COMPONENTS], axis=0)
    unsaturated = np.abs(summed) < 0.1 - 1e-9
    residual = np.abs(summed - delta_q)[unsaturated]
    return {
        "components": stats,
        "ranking": sorted(COMPONENTS, key=lambda n: -stats[n]["rms"]),
        "ranking_std": sorted(COMPONENTS, key=lambda n: -stats[n]["std"]),
        "delta_q_rms": float(np.sqrt(np.mean(delta_q**2))),
        "sum_residual_max": float(residual.max()) if residual.size else 0.0,
        "samples": int(window.sum()),
    }


def analyse_components(
    motion_signals: dict[str, dict[str, np.ndarray]],
    force_signals: dict[str, np.ndarray],
    out: Path | None = None,
    motion_start: float | None = None,
    force_start: float | None = None,
) -> dict:
    """The contribution of each component of Δq in the paper's six panels, the check
    of its conclusions, and (with `out`) components.md, components.json and
    figure6_components.png.

    Args:
        motion_signals: the motion experiment's logged signals by run label
            (`MotionResult.signals`); the runs at K6 = 0.1 and K6 = 1 are used.
        force_signals: the force experiment's logged signals (`ForceRun.signals`, or
            `force.load_signals` of force_signals.npz).
        out: the report's folder (nothing is written if None).
        motion_start, force_start: start of the analysed windows (s); default: see
            the module docstring.

    Returns:
        {"panels": {key: {title, experiment, k6, joint, statistics..., expected,
        holds}}, "conclusions": {"motion": bool, "force": bool}}.
    """
    runs = {k6: find_motion_run(motion_signals, k6) for k6 in MOTION_K6}
    panels = {}
    for panel in PANELS:
        if panel.experiment == "motion":
            signals = motion_signals[runs[panel.k6]]
            window = motion_window(signals, motion_start)
            source = runs[panel.k6]
        else:
            signals = force_signals
            window = force_window(signals, force_start)
            source = "force control"
        stats = component_statistics(signals, panel.joint, window)
        panels[panel.key] = {
            "title": panel.title,
            "experiment": panel.experiment,
            "run": source,
            "k6": panel.k6,
            "joint": panel.joint,
            "window_start": float(signals["t"][np.argmax(window)]),
            **stats,
            "expected": [panel.first, *panel.next],
            "holds": check_panel(panel, stats["ranking"]),
            "holds_std": check_panel(panel, stats["ranking_std"]),
        }
    summary = {
        "panels": panels,
        "conclusions": {
            experiment: all(
                panels[p.key]["holds"] for p in PANELS if p.experiment == experiment
            )
            for experiment in ("motion", "force")
        },
        "conclusions_std": {
            experiment: all(
                panels[p.key]["holds_std"] for p in PANELS if p.experiment == experiment
            )
            for experiment in ("motion", "force")
        },
    }
    if out is not None:
        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        (out / "components.json").write_text(json.dumps(summary, indent=2))
        figure = plot_figure6(
            motion_signals, runs, force_signals, summary, out, motion_start, force_start
        )
        (out / "components.md").write_text(_markdown(summary, figure))
    return summary


def _markdown(summary: dict, figure: str) -> str:
    lines = [
        "# Control components (paper Sec. 5.5, Figure 6)",
        "",
        "Contribution of each component of Δq: RMS over the analysed window in mrad "
        "(share of the sum of the six RMS). Motion: the climbing swing (hanging); "
        "force: the sinusoidal force on the right foot (standing on the block).",
        "",
        *_component_table(summary["panels"], "rms"),
        "",
        "The same with the standard deviation (the varying part only; ranking and "
        "verdict):",
        "",
        *_component_table(summary["panels"], "std"),
    ]
    c, cs = summary["conclusions"], summary["conclusions_std"]
    lines += [
        "",
        "## The paper's conclusions, by numbers",
        "",
        '- Motion control, "feedforward friction" most, then "feedback position": '
        + ("holds" if c["motion"] else "does not hold")
        + " on RMS, "
        + ("holds" if cs["motion"] else "does not hold")
        + " on the varying part.",
        '- Force control, "feedforward torque" most, then "feedback force" (and '
        '"feedback position" for the ankle pitch): '
        + ("holds" if c["force"] else "does not hold")
        + " on RMS, "
        + ("holds" if cs["force"] else "does not hold")
        + " on the varying part.",
        "",
        "Check: the six components add up to the Δq sent to the servo within "
        + f"{max(p['sum_residual_max'] for p in summary['panels'].values()):.1e} rad "
        "(unsaturated samples).",
        "",
        f"![{figure}]({figure})",
        "",
    ]
    return "\n".join(lines)


def _component_table(panels: dict, statistic: str) -> list[str]:
    """One row per panel: each component's `statistic` ("rms" or "std", mrad) with
    its share of the six, the three largest, and the paper's conclusion judged on
    them (named in full on the RMS table)."""
    suffix = "" if statistic == "rms" else f"_{statistic}"
    rows = []
    for p in panels.values():
        stats = p["components"]
        cells = [
            f"{stats[c][statistic] * 1e3:.3f} ({stats[c]['share' + suffix]:.0%})"
            for c in COMPONENTS
        ]
        ranking = " > ".join(COMPONENT_LABELS[c] for c in p["ranking" + suffix][:3])
        verdict = "holds" if p["holds" + suffix] else "**does not hold**"
        if statistic == "rms":
            expected = (
                COMPONENT_LABELS[p["expected"][0]]
                + ", then "
                + " and ".join(COMPONENT_LABELS[c] for c in p["expected"][1:])
            )
            verdict = f"{expected}: {verdict}"
        rows.append([p["title"], *cells, ranking, verdict])
    name = {"rms": "RMS"}.get(statistic, statistic)
    header = ["panel", *(COMPONENT_LABELS[c] for c in COMPONENTS)]
    header += [f"ranking ({name})", "paper's conclusion"]
    return markdown_table(header, rows, align="l" + "r" * len(COMPONENTS) + "ll")


def plot_figure6(
    motion_signals: dict,
    runs: dict[float, str],
    force_signals: dict,
    summary: dict,
    out: Path,
    motion_start: float | None = None,
    force_start: float | None = None,
) -> str:
    """Fig. 6: the components of Δq over time (mrad) in the six panels, each
    legend, beside its panel (off the data), with the component's RMS share."""
    plt = pyplot()
    colors = dict(zip(COMPONENTS, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    fig, axes = plt.subplots(3, 2, figsize=(17, 10), layout="constrained")
    for ax, panel in zip(axes.ravel(), PANELS):
        if panel.experiment == "motion":
            signals = motion_signals[runs[panel.k6]]
            window = motion_window(signals, motion_start)
        else:
            signals = force_signals
            window = force_window(signals, force_start)
        k = hrp2.RIGHT_LEG.index(panel.joint)
        t = signals["t"][window]
        stats = summary["panels"][panel.key]["components"]
        for name in COMPONENTS:
            main = name in (
                "feedforward_torque",
                "feedforward_friction",
                "feedback_position",
                "feedback_force",
            )
            ax.plot(
                t,
                signals[name][window, k] * 1e3,
                lw=1.0 if main else 0.6,
                alpha=1.0 if main else 0.6,
                color=colors[name],
                label=f"{COMPONENT_LABELS[name]} ({stats[name]['share']:.0%})",
            )
        ax.set_title(panel.title, fontsize=10)
        ax.set_ylabel("Δq component (mrad)")
        ax.grid(True, alpha=0.3)
        legend_beside(ax, fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("t (s)")
    fig.suptitle("Figure 6: components of Δq (share of the RMS in the legend)")
    name = "figure6_components.png"
    save_figure(fig, out / name)
    return name
