"""`hrp2-drake simulate`: run a scenario with the servo holding a pose or following a
trajectory, log every station signal at 1 kHz, optionally record a Meshcat replay;
write the run (`write_simulation`).
"""

import json
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Diagram, DiagramBuilder
from pydrake.systems.primitives import (
    ConstantVectorSource,
    TrajectorySource,
    VectorLogSink,
)

from hrp2_drake.config import check_finite
from hrp2_drake.description import RobotDescription, check_joint_positions
from hrp2_drake.robot.station import (
    StationConfig,
    initial_joint_positions,
    make_station,
)
from hrp2_drake.simulation import (
    add_loggers,
    joint_reference,
    logs_to_arrays,
    run_with_progress,
)


@dataclass
class SimulateConfig:
    """Configuration of `hrp2-drake simulate`.

    Args:
        station: the simulated robot.
        duration: simulated time (s).
        trajectory: "" to hold the scenario's initial pose (HRP-2: half-sitting),
            "default" (or "climbing") for the robot description's trajectory_file
            (HRP-2: its stair-climbing motion), or a path to a text file in the same
            format (time, then the robot's joint angles in its joint order, rad).
        trajectory_start: time (s) at which the trajectory starts (held before).
        log_period: period of the logged signals (s).
    """

    station: StationConfig = field(
        default_factory=lambda: StationConfig(scenario="standing")
    )
    duration: float = 5.0
    trajectory: str = ""
    trajectory_start: float = 0.5
    log_period: float = 0.001

    def validate(self) -> None:
        """Raises ValueError naming the bad field; reads the trajectory file (if any)
        so that a bad one is reported before anything is simulated."""
        self.station.validate()
        for name, low, strict in (
            ("duration", 0.0, True),
            ("trajectory_start", 0.0, False),
            ("log_period", 0.0, True),
        ):
            check_finite(getattr(self, name), f"SimulateConfig.{name}", low, strict)
        if self.log_period > self.duration:
            raise ValueError(
                f"SimulateConfig.log_period: {self.log_period:g} s is longer than the "
                f"run (duration {self.duration:g} s): the log would hold one sample"
            )
        if self.log_period < self.station.time_step * (1 - 1e-9):
            raise ValueError(
                f"SimulateConfig.log_period: {self.log_period:g} s is shorter than the "
                f"plant's time step ({self.station.time_step:g} s): samples would "
                "repeat"
            )
        robot = self.station.description()
        if self.trajectory:
            load_joint_trajectory(self.trajectory, robot)


def check_joint_limits(
    q: np.ndarray,
    where: str,
    robot: RobotDescription | None = None,
    tolerance: float = 1e-9,
) -> None:
    """Raises ValueError naming `where`, the first offending joint and row unless every
    row of q (m, n) lies within the robot's joint position limits (default: HRP-2)."""
    check_joint_positions(q, where, robot or StationConfig().description(), tolerance)


def load_joint_trajectory(
    spec: str, robot: RobotDescription | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(t, q) of the robot's own ("default", or "climbing" for HRP-2) or a file
    trajectory; q has a column per joint of the robot (default: HRP-2).

    A file is text, one row per sample: the time (s), then the n joint angles (rad)
    in the robot's joint order. Raises (naming the file) unless it has exactly n + 1
    columns, at least two rows, finite numbers, strictly increasing times and angles
    within the joints' position limits (the model's).
    """
    robot = robot or StationConfig().description()
    n = len(robot.joints)
    if spec in ("default", "climbing"):
        if not robot.trajectory_file:
            raise ValueError(
                f"trajectory '{spec}': robot '{robot.name}' has no trajectory_file"
            )
        return robot.load_trajectory()
    path = Path(spec)
    if not path.exists():
        raise FileNotFoundError(f"trajectory file '{spec}' not found")
    if path.is_dir():
        raise IsADirectoryError(f"trajectory file '{spec}' is a folder")
    columns = 1 + n
    try:
        with warnings.catch_warnings():  # an empty file: reported below, not warned
            warnings.simplefilter("ignore", UserWarning)
            data = np.loadtxt(path, ndmin=2)
    except (ValueError, UnicodeDecodeError) as error:
        detail = "; ".join(str(error).splitlines())
        raise ValueError(
            f"trajectory file '{spec}': not a text table of numbers "
            f"(time + {n} joint angles per row): {detail}"
        ) from None
    if data.size == 0:
        raise ValueError(
            f"trajectory file '{spec}': empty, expected rows of time + {n} joint angles"
        )
    if data.shape[1] != columns or data.shape[0] < 2:
        raise ValueError(
            f"trajectory file '{spec}': {data.shape[0]} rows of {data.shape[1]} "
            f"columns, expected at least 2 rows of exactly {columns} (time + "
            f"{n} joint angles)"
        )
    if not np.all(np.isfinite(data)):
        row = int(np.argwhere(~np.isfinite(data))[0, 0])
        raise ValueError(f"trajectory file '{spec}': NaN or inf in row {row}")
    t, q = data[:, 0], data[:, 1:]
    steps = np.diff(t)
    if np.any(steps <= 0):
        row = int(np.flatnonzero(steps <= 0)[0]) + 1
        raise ValueError(
            f"trajectory file '{spec}': the time column must be strictly increasing, "
            f"row {row} has t = {t[row]:g} s after {t[row - 1]:g} s"
        )
    check_joint_limits(q, f"trajectory file '{spec}'", robot)
    return t, q


def station_logged_ports(robot: RobotDescription) -> tuple[str, ...]:
    """The station ports `simulate` logs: every sensor, and the ground truth."""
    from hrp2_drake.robot.station import sensor_sizes

    return (*sensor_sizes(robot), "joint_torque_true", "state_true")


@dataclass
class SimulationResult:
    """Logged signals ({"t", port name, "q_cmd"} -> array) and run statistics."""

    signals: dict[str, np.ndarray]
    real_time_factor: float
    html: str | None = None


def build_simulation(
    config: SimulateConfig, meshcat=None
) -> tuple[Diagram, Diagram, dict[str, VectorLogSink]]:
    """(diagram, station, loggers) for `config` (validated where it was loaded,
    `validate_config`): station + q_cmd source + loggers."""
    builder = DiagramBuilder()
    station = builder.AddNamedSystem("station", make_station(config.station, meshcat))
    robot = config.station.description()
    if config.trajectory:
        t, q = load_joint_trajectory(config.trajectory, robot)
        source = TrajectorySource(joint_reference(t, q, config.trajectory_start))
    else:
        source = ConstantVectorSource(initial_joint_positions(config.station))
    source = builder.AddNamedSystem("q_cmd_source", source)
    builder.Connect(source.get_output_port(), station.GetInputPort("q_cmd"))
    ports = {name: station.GetOutputPort(name) for name in station_logged_ports(robot)}
    ports["q_cmd"] = source.get_output_port()
    loggers = add_loggers(builder, ports, config.log_period)
    return builder.Build(), station, loggers


def run_simulate(config: SimulateConfig, html: bool = False) -> SimulationResult:
    """Runs `config`, returning the logged signals (and a Meshcat HTML replay)."""
    meshcat = None
    if html:
        from pydrake.geometry import Meshcat

        meshcat = Meshcat()
    diagram, _, loggers = build_simulation(config, meshcat)
    simulator = Simulator(diagram)
    if meshcat is not None:
        meshcat.StartRecording(frames_per_second=30.0)
    rtf = run_with_progress(
        simulator, config.duration, f"simulate {config.station.scenario}"
    )
    replay = None
    if meshcat is not None:
        meshcat.StopRecording()
        meshcat.PublishRecording()
        replay = meshcat.StaticHtml()
    signals = logs_to_arrays(loggers, simulator.get_context())
    return SimulationResult(signals, rtf, replay)


def summarize(result: SimulationResult, config: SimulateConfig) -> dict[str, float]:
    """Numbers a user checks first: tracking, base drift, torques."""
    s = result.signals
    q_err = s["q_cmd"] - s["q_measured"]
    summary = {
        "duration_s": float(s["t"][-1]),
        "real_time_factor": result.real_time_factor,
        "max_abs_tracking_error_rad": float(np.abs(q_err).max()),
        "max_abs_joint_torque_Nm": float(np.abs(s["joint_torque_true"]).max()),
    }
    if (
        config.station.scenario != "fixed_base"
    ):  # the base's free joint: [quaternion; xyz]
        base_xyz = s["state_true"][:, 4:7]
        summary["base_drift_m"] = float(np.linalg.norm(base_xyz[-1] - base_xyz[0]))
        summary["base_height_final_m"] = float(base_xyz[-1, 2])
    return summary


def write_simulation(
    result: SimulationResult, config: SimulateConfig, out: Path
) -> tuple[dict[str, Path], dict[str, float]]:
    """Writes the run under `out`, named by its scenario: the logged signals
    (simulate_<scenario>.npz), its summary (`summarize`, .json) and, if recorded, its
    Meshcat replay (.html). Returns (the files by kind: "log", "summary", "replay";
    the summary)."""
    stem = out / f"simulate_{config.station.scenario}"
    files = {"log": stem.with_suffix(".npz"), "summary": stem.with_suffix(".json")}
    np.savez_compressed(files["log"], **result.signals)
    summary = summarize(result, config)
    files["summary"].write_text(json.dumps(summary, indent=2))
    if result.html is not None:
        files["replay"] = stem.with_suffix(".html")
        files["replay"].write_text(result.html)
    return files, summary
