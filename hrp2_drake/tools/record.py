"""`hrp2-drake record --robot R --port DEV`: a robot's identification logs, recorded
through its servo bus. A user's first step on a real robot.

The servos' own position control plays the description's identification excitation
(`RobotDescription.identification`: one increasing sinusoid per joint, paper Sec.
3.4.2; pushes, if the description has them, are holds where a person pushes), after
a smooth move from the measured pose to its start, once per position P gain of
`gains`. Every period: one sync read (the measured positions, and whatever else the
bus reads), one sync write (the goal). Each log is written in the robot's own log
format (`RobotDescription.logs`), which `identify`, `validate` and `calibrate` read:
its time column is the host's clock at the middle of each sync read (a lock-step
robot's: the periods' times), its command the goal as the servos took it (whole
pulses), its valid column 1 (torque on), its gain the P gain set.

Writes one log per gain, record.md (a table of the logs, the bus's faults, a plot of
each) and record.json.
"""

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from hrp2_drake.assembly.builders import SmoothMove
from hrp2_drake.config import check_finite
from hrp2_drake.console import say
from hrp2_drake.description import RobotDescription, load_robot_description
from hrp2_drake.hardware.bus_link import BusLink
from hrp2_drake.hardware.control_loop import LoopSettings
from hrp2_drake.hardware.link import LinkClosed, LoopFault
from hrp2_drake.hardware.real_time import garbage_collector_frozen
from hrp2_drake.identification.excitation import make_plan
from hrp2_drake.identification.logs import write_robot_log
from hrp2_drake.report import legend_beside, markdown_table, pyplot, save_figure


@dataclass
class RecordConfig:
    """Configuration of `hrp2-drake record`.

    Args:
        robot: the robot's description (one with a `bus`): a robot.yaml path or the
            name of a robot in models/.
        gains: the position P gains to record at (the servos' units), one log each:
            logs at two gains let identification pool them and calibration see the
            gain's effect; empty: the description's position_loop.gain.
        duration_scale: the excitation's sinusoids lengthened (> 1) or shortened
            (< 1; each at least 2 s).
        approach_speed: the move from the measured pose to the excitation's start:
            its fastest joint (rad/s).
        loop: the loop's settings (its real_time.freeze_gc; a period that starts
            more than a period late skips to the period of now, counted in the
            report).
    """

    robot: str = ""
    gains: list[float] = field(default_factory=list)
    duration_scale: float = 1.0
    approach_speed: float = 0.5
    loop: LoopSettings = field(default_factory=LoopSettings)

    def description(self) -> RobotDescription:
        return load_robot_description(self.robot or None)

    def gains_to_record(self) -> list[float]:
        return list(self.gains) or [self.description().position_loop.gain]

    def validate(self) -> None:
        robot = self.description()
        where = "RecordConfig"
        if not robot.bus.active:
            raise ValueError(
                f"{where}.robot: '{robot.name}' has no bus in its description "
                "(bus.kind)"
            )
        if robot.identification.is_empty():
            raise ValueError(
                f"{where}.robot: '{robot.name}' has no identification excitation in "
                "its description (identification.sinusoids)"
            )
        model = robot.bus.servo_model()
        low, high = model.register("position_p_gain").limits()
        for k, gain in enumerate(self.gains_to_record()):
            if not (gain == int(gain) and 1 <= gain <= high):
                raise ValueError(
                    f"{where}.gains[{k}]: {gain:g}, a Position P Gain of the "
                    f"{robot.bus.model} is an integer from 1 to {high}"
                )
        check_finite(self.duration_scale, f"{where}.duration_scale", 0.0)
        check_finite(self.approach_speed, f"{where}.approach_speed", 0.0)
        self.loop.validate(robot.sensors.period, f"{where}.loop")


class _Excitation:
    """The goal over time: a smooth move from the measured pose to the plan's start
    (`SmoothMove`), then the plan (`make_plan`'s q_cmd)."""

    def __init__(self, plan, start: np.ndarray, speed: float):
        self.plan = plan
        self.move = SmoothMove(start, plan.q_cmd.value(0.0).ravel(), speed)
        self.approach = self.move.duration
        self.end = self.approach + plan.duration

    def __call__(self, t: float) -> np.ndarray:
        if t < self.approach:
            return self.move.at(np.array([t]))[0][0]
        return self.plan.q_cmd.value(min(t - self.approach, self.plan.duration)).ravel()


def record_one(
    robot: RobotDescription,
    port: str,
    gain: float,
    config: RecordConfig,
    lockstep: bool,
) -> dict:
    """One log at P gain `gain`: its columns (`write_robot_log`'s), the link's
    counters and why it stopped ("" at its end)."""
    bus = robot.bus
    n = len(robot.joints)
    buffers = SimpleNamespace(q_measured=np.zeros(n), q_measured_time=np.zeros(1))
    link = BusLink(robot, port, lockstep=lockstep, gain=gain, skip_late=True)
    try:
        start = link.connect(buffers)
        plan = make_plan(
            robot.identification.scaled(config.duration_scale),
            robot.joints,
            robot.home_positions(),
        )
        excitation = _Excitation(plan, start, config.approach_speed)
        with garbage_collector_frozen(config.loop.real_time.freeze_gc):
            rows, fault = _play(link, buffers, excitation, config, lockstep)
    finally:
        link.close()
    columns = _columns(robot, rows)
    return {
        "gain": gain,
        "columns": columns,
        "counters": link.counters(),
        "fault": fault,
        "approach": excitation.approach,
        "rate": 1.0 / robot.sensors.period,
        "bus": bus,
    }


def _play(
    link: BusLink,
    buffers,
    excitation: _Excitation,
    config: RecordConfig,
    lockstep: bool,
) -> tuple[list, str]:
    """Each period: read, log, write the goal; until the excitation's end or a fault.
    Progress: a line every tenth of the excitation (between periods)."""
    rows, fault = [], ""
    t0 = time.perf_counter_ns()
    timeout = config.loop.silence_timeout
    next_report = 0.1
    while True:
        try:
            t = link.receive(buffers, timeout)
            stamp = (
                t
                if lockstep
                else ((link.started_ns + link.received_ns) / 2 - t0) * 1e-9
            )
            goal = link.robot.bus.quantized(excitation(t))
            rows.append(
                (
                    stamp,
                    buffers.q_measured.copy(),
                    goal,
                    {k: v.copy() for k, v in link.reading.values.items()},
                )
            )
            link.send(goal, t)
        except LoopFault as error:
            fault = str(error)
            break
        except LinkClosed as error:
            fault = link.gone(error)
            break
        if t >= excitation.end:
            break
        if t >= next_report * excitation.end:
            say(f"recording: {t:.1f}/{excitation.end:.1f} s")
            next_report += 0.1
    return rows, fault


def _columns(robot: RobotDescription, rows: list) -> dict[str, np.ndarray]:
    """The log's columns by the names of the robot's log format."""
    log_format = robot.logs
    columns = {log_format.time: np.array([r[0] for r in rows])}
    positions = np.array([r[1] for r in rows]) / log_format.position_unit
    goals = np.array([r[2] for r in rows]) / log_format.position_unit
    for j, (p_key, c_key) in enumerate(zip(log_format.position, log_format.command)):
        columns[p_key] = positions[:, j]
        columns[c_key] = goals[:, j]
    if log_format.valid:
        columns[log_format.valid] = np.ones(len(rows))
    one = len(robot.joints) == 1
    for item in robot.bus.read:
        if item == "present_position":
            continue
        values = np.array([r[3][item] for r in rows])
        for j, joint in enumerate(robot.joints):
            columns[item if one else f"{item}_{joint}"] = values[:, j]
    return columns


def run_record(
    config: RecordConfig, port: str, out: Path, lockstep: bool = False
) -> dict:
    """The whole `hrp2-drake record` (module docstring); the summary."""
    config.validate()
    robot = config.description()
    if robot.logs.format == "npz":
        raise ValueError(
            f"robot '{robot.name}': its log format is this project's npz; record "
            "writes a robot's own format (logs.format json or csv)"
        )
    out.mkdir(parents=True, exist_ok=True)
    logs = []
    for gain in config.gains_to_record():
        say(f"recording {robot.name} at P gain {gain:g} on {port}")
        one = record_one(robot, port, gain, config, lockstep)
        name = f"{robot.name}_kp{gain:g}.{robot.logs.format}"
        meta = {robot.logs.gain: gain} if robot.logs.gain else {}
        meta |= {"robot": robot.name, "port": port, "bus_period": robot.sensors.period}
        write_robot_log(out / name, robot.logs, one["columns"], meta)
        _plot(robot, one, out / f"{Path(name).stem}.png")
        logs.append(
            {
                "log": name,
                "gain": gain,
                "samples": len(one["columns"][robot.logs.time]),
                "approach_s": one["approach"],
                "fault": one["fault"],
                "bus": one["counters"],
            }
        )
        if one["fault"]:
            break
    summary = {"robot": robot.name, "port": port, "lockstep": lockstep, "logs": logs}
    (out / "record.json").write_text(json.dumps(summary, indent=2))
    (out / "record.md").write_text(_markdown(robot, summary))
    return summary


def _plot(robot: RobotDescription, one: dict, path: Path) -> None:
    columns, log_format = one["columns"], robot.logs
    t = columns[log_format.time]
    fig, axes = pyplot().subplots(
        len(robot.joints), 1, figsize=(9, 2.5 * len(robot.joints)), squeeze=False
    )
    for ax, label, p_key, c_key in zip(
        axes[:, 0],
        robot.joint_labels or robot.joints,
        log_format.position,
        log_format.command,
    ):
        ax.plot(
            t, columns[c_key] * log_format.position_unit, "k--", lw=0.8, label="goal"
        )
        ax.plot(t, columns[p_key] * log_format.position_unit, lw=1.0, label="measured")
        ax.set_ylabel(f"{label} (rad)")
        legend_beside(ax)
    axes[-1, 0].set_xlabel("t (s)")
    save_figure(fig, path, dpi=90, tight=True)


def _markdown(robot: RobotDescription, summary: dict) -> str:
    bus = robot.bus
    rows = []
    for log in summary["logs"]:
        servos = log["bus"]["servos"].values()
        faults = sum(c["no_status"] + c["corrupt"] for c in servos)
        rows.append(
            [
                f"`{log['log']}`",
                f"{log['gain']:g}",
                f"{log['samples']}",
                f"{log['approach_s']:.1f}",
                f"{faults}",
                f"{log['bus']['late_periods']} ({log['bus']['skipped_periods']})",
                log["fault"] or "its end",
            ]
        )
    lines = [
        f"# Identification logs of {robot.name}, recorded on its bus",
        "",
        f"Port {summary['port']}"
        + (" (a lock-step robot)" if summary["lockstep"] else "")
        + f": {len(bus.ids)} {bus.model} servo(s) at {bus.baud / 1e6:g} Mbit/s, one "
        f"sync read and one sync write every {robot.sensors.period * 1e3:g} ms. The "
        "servos' own position control played the description's identification "
        "excitation, after a move from the measured pose to its start. Read them with "
        f"`hrp2-drake identify --robot {robot.name} --log <log>` (and `validate`, "
        "`calibrate`).",
        "",
        *markdown_table(
            [
                "log",
                "P gain",
                "samples",
                "move to start (s)",
                "statuses missing or corrupt",
                "late periods (skipped)",
                "ended with",
            ],
            rows,
        ),
        "",
        *[f"![{log['log']}]({Path(log['log']).stem}.png)" for log in summary["logs"]],
    ]
    return "\n".join(lines) + "\n"
