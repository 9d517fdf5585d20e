"""`hrp2-drake balance --robot hrp2`: a floating-base robot standing on its soles,
balanced by torque control (the whole-body QP with contacts over the paper's Δq
controller of the legs: `assembly.balance.build_balance_control`) and by the robot's
own position control (the same CoM reference through inverse kinematics, the stock
servo tracking it: `build_position_control`), side by side (issue 29).

Two experiments, each under both controls:

1. **CoM tracking, the authors' protocol** (sot-torque-control's balance test on
   HRP-2): the CoM shifts to +3 cm along y, then follows a sinusoid between +3 and
   −3 cm with a 2 s period, for 10 s. Reported: the RMS and maximum CoM error (the
   true CoM against its reference), the CoP margin (the smallest distance from each
   loaded sole's centre of pressure to its edge), the soles' peak normal forces,
   and, under torque control, the RMS of τ̂ against the true joint torques of the
   legs t_d earlier, t_d the estimation delay (the paper's definition of the
   estimate; against this project's 3%-of-peak goal), and against those of the
   same instant.
2. **Pushes**: a horizontal force pulse (0.1 s) on the torso (the description's
   `unknown_wrench_body`), forward and sideways, increasing (doubled, then bisected)
   until the robot fails: a sole slides or lifts (`sole_slip`) or rotates
   (`sole_tilt`: the heel or the toes lift), the base drops (`fall_drop`), or, under
   torque control, the supervisor hands the robot back to position control.
   Reported: the largest push survived by each control; at the largest push both
   survive, the CoM's excursion, the soles' peak normal forces and the time to
   settle; why each control failed.

The contact forces, the centre of pressure and the CoM are ground truth (Drake's
contact results and the plant's state), for evaluation only; the controllers read
the sensors. The motor model is identified first (`hrp2-drake identify`) unless one
is given: the description's identification, then each `identify_*.yaml` of the
robot's folder (HRP-2: the left leg's), merged.

Writes balance.md (`experiments.balance.report`, from the summary alone), balance.json
and figures. Nothing here knows a robot's names.
"""

import json
import math
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field, replace
from multiprocessing import get_context
from pathlib import Path

import numpy as np
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.primitives import TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake import console
from hrp2_drake.assembly.balance import (
    BalanceControlConfig,
    build_balance_control,
    resolved,
    robot_model,
    sole_poses,
)
from hrp2_drake.assembly.builders import JointReference, build_position_control
from hrp2_drake.config import check_finite
from hrp2_drake.control.balance import BALANCE_FAULTS
from hrp2_drake.control.balance_reference import ComSinusoid, StandingIk, sinusoid_com
from hrp2_drake.control.safety import describe_faults
from hrp2_drake.description import RobotDescription
from hrp2_drake.estimation.accuracy import errors
from hrp2_drake.estimation.estimator_config import GOAL_RMS_OVER_PEAK
from hrp2_drake.experiments.balance.calibration import CalibrationSettings, calibrate
from hrp2_drake.experiments.balance.report import MODES, report_markdown
from hrp2_drake.identification.excitation import PushSource
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.report import legend_beside, pyplot, save_figure
from hrp2_drake.robot.ground_truth import SoleContacts
from hrp2_drake.robot.station import (
    StationConfig,
    initial_joint_positions,
    make_station,
    standing_positions,
)
from hrp2_drake.simulation import add_loggers, logs_to_arrays, run_with_progress

_WHERE = "BalanceExperimentConfig"
#: Push directions: the unit force in the world.
DIRECTIONS = {"forward": (1.0, 0.0, 0.0), "sideways": (0.0, 1.0, 0.0)}
#: A sole carrying less than this (N) is not loaded: its CoP is not counted.
LOADED_SOLE = 20.0
#: The logs' period (s) and the metrics' (the CoM and the soles from the state).
LOG_PERIOD = 0.001
METRIC_STRIDE = 5


@dataclass
class ComMotion(ComSinusoid):
    """The authors' CoM motion (`ComSinusoid`) for `duration` (s): how long the
    sinusoid runs."""

    duration: float = 10.0

    def validate(self) -> None:
        where = f"{_WHERE}.com_motion"
        super().validate(where)
        check_finite(self.duration, f"{where}.duration", 0.0)

    def total(self) -> float:
        return self.shift_time + self.hold_time + self.duration


@dataclass
class PushSettings:
    """The pushes and what counts as a failure.

    Args:
        body: the pushed body; empty: the description's `unknown_wrench_body` (the
            torso on HRP-2).
        point: where, in the body's frame (m).
        duration: the pulse's (s).
        directions: among "forward", "sideways".
        first: the first force tried (N); doubled until a control fails, then
            bisected down to `resolution` (N), up to `largest` (N).
        observe: how long after the pulse a run goes on (s).
        sole_slip: a sole that moves this far (m) from where it stood slid or lifted.
        sole_tilt: a sole that tilts this much (rad) rotated: its heel or toes
            lifted (far above what the compliant contact tilts a flat sole: the
            report's CoM table gives the largest tilt along the sinusoid).
        fall_drop: a base that drops this far (m) fell.
        settled: the CoM is settled once within this distance (m) of where it was
            before the push, for the rest of the run.
    """

    body: str = ""
    point: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    duration: float = 0.1
    directions: list[str] = field(default_factory=lambda: ["forward", "sideways"])
    first: float = 50.0
    resolution: float = 10.0
    largest: float = 3200.0
    observe: float = 2.5
    sole_slip: float = 0.005
    sole_tilt: float = 0.01
    fall_drop: float = 0.05
    settled: float = 0.002

    def validate(self) -> None:
        where = f"{_WHERE}.pushes"
        unknown = [d for d in self.directions if d not in DIRECTIONS]
        if unknown:
            raise ValueError(
                f"{where}.directions: {unknown}, expected among {list(DIRECTIONS)}"
            )
        if len(self.point) != 3:
            raise ValueError(f"{where}.point: {self.point}, expected [x, y, z] (m)")
        for name in (
            "duration",
            "first",
            "resolution",
            "largest",
            "observe",
            "sole_slip",
            "sole_tilt",
            "fall_drop",
            "settled",
        ):
            check_finite(getattr(self, name), f"{where}.{name}", 0.0)
        if self.first > self.largest:
            raise ValueError(
                f"{where}.first: {self.first} N is above largest ({self.largest} N)"
            )


@dataclass
class BalanceExperimentConfig:
    """Configuration of `hrp2-drake balance` (module docstring).

    Args:
        station: the simulated robot, standing (its servo: the description's,
            calibrated to the real robot on HRP-2).
        control: the balance QP and the Δq chain of the legs.
        settle: torque control starts at `control.torque.start_time`; the CoM motion
            and the pushes wait until `settle` (s).
        com_motion: the CoM tracking experiment.
        pushes: the push experiment.
        calibration: the start-up calibration, as the authors calibrated the real
            HRP-2 (`experiments.balance.calibration`): the F/T offsets found lifted, the
            CoM offset put down; what it finds goes into `control` (the estimator's
            offsets, the CoM offset) before the runs.
        workers: processes running the simulations in parallel.
        fused: the torque-control chain as one `FusedTorqueController` (the
            real-time path, the separate systems' numbers to 1e-12, faster to
            simulate) or as its separate LeafSystems.
    """

    station: StationConfig = field(
        default_factory=lambda: StationConfig(scenario="standing")
    )
    control: BalanceControlConfig = field(default_factory=BalanceControlConfig)
    settle: float = 1.0
    com_motion: ComMotion = field(default_factory=ComMotion)
    pushes: PushSettings = field(default_factory=PushSettings)
    calibration: CalibrationSettings = field(default_factory=CalibrationSettings)
    workers: int = 2
    fused: bool = True

    def validate(self) -> None:
        if self.station.scenario != "standing":
            raise ValueError(
                f"{_WHERE}.station.scenario: '{self.station.scenario}', the balance "
                "experiments need 'standing'"
            )
        self.station.validate()
        robot = self.station.description()
        robot_model(robot)  # a floating base with soles
        self.control.validate()
        self.com_motion.validate()
        self.pushes.validate()
        self.calibration.validate()
        if self.calibration.enabled and not robot.scenarios.hanging.body:
            raise ValueError(
                f"{_WHERE}.calibration.enabled: robot '{robot.name}' has no "
                "scenarios.hanging to be lifted by (its F/T offsets are found lifted): "
                "describe its strings, or set calibration: {enabled: false}"
            )
        check_finite(self.settle, f"{_WHERE}.settle", 0.0)
        if self.settle < self.control.torque.start_time:
            raise ValueError(
                f"{_WHERE}.settle: {self.settle} s is before torque control starts "
                f"(control.torque.start_time {self.control.torque.start_time} s)"
            )
        if self.workers < 1:
            raise ValueError(f"{_WHERE}.workers: {self.workers}, expected >= 1")
        body = self.push_body(robot)
        if not body:
            raise ValueError(
                f"{_WHERE}.pushes.body: empty, and robot '{robot.name}' names no "
                "unknown_wrench_body"
            )

    def push_body(self, robot: RobotDescription) -> str:
        return self.pushes.body or robot.unknown_wrench_body


# ------------------------------------------------------------------ the runs


@dataclass
class RunSpec:
    """One simulation: a control, a CoM motion or a push."""

    mode: str  # "torque" or "position"
    kind: str  # "com" or "push"
    direction: str = ""
    force: float = 0.0


def _com_axis(config: BalanceExperimentConfig) -> int:
    return "xyz".index(config.com_motion.axis)


def _references(config: BalanceExperimentConfig, spec: RunSpec):
    """(joint reference, CoM reference (9 rows), standing positions, duration)."""
    robot = config.station.description()
    q0 = initial_joint_positions(config.station)
    standing = standing_positions(robot, q0)
    plant = robot_model(robot)
    ik = StandingIk(plant, robot.joints, list(robot.contacts.soles), standing)
    com0 = ik.com(standing)
    if spec.kind == "com":
        duration = config.settle + config.com_motion.total()
    else:
        duration = config.settle + config.pushes.duration + config.pushes.observe
    t = np.arange(0.0, duration + 0.0105, 0.01)
    motion = config.com_motion
    if spec.kind == "com":
        com = sinusoid_com(
            com0,
            t - config.settle,
            amplitude=motion.amplitude,
            period=motion.period,
            shift_time=motion.shift_time,
            hold_time=motion.hold_time,
            axis=_com_axis(config),
        )
        com[t < config.settle] = np.r_[com0, np.zeros(6)]
    else:
        com = np.tile(np.r_[com0, np.zeros(6)], (len(t), 1))
    positions = ik.trajectory(com[:, :3])
    q = np.array([ik.joint_angles(p) for p in positions])
    v = np.gradient(q, t, axis=0)
    a = np.gradient(v, t, axis=0)
    reference = JointReference.from_samples(t, q, v, a)
    return (
        reference,
        PiecewisePolynomial.FirstOrderHold(t, com.T),
        standing,
        duration,
    )


def _push_wrench(config: BalanceExperimentConfig, spec: RunSpec) -> PiecewisePolynomial:
    """The pulse [torque; force] (world): zero, the force over `duration` from
    `settle`, zero."""
    t0, t1 = config.settle, config.settle + config.pushes.duration
    force = spec.force * np.array(DIRECTIONS[spec.direction])
    wrench = np.r_[np.zeros(3), force]
    times = [0.0, t0, t1, t1 + 10.0]
    values = np.column_stack([np.zeros(6), wrench, np.zeros(6), np.zeros(6)])
    return PiecewisePolynomial.ZeroOrderHold(times, values)


def simulate_run(
    config: BalanceExperimentConfig, motor_model: MotorModel, spec: RunSpec
) -> dict:
    """One run's logs at 1 kHz (arrays by name) and its metrics."""
    robot = config.station.description()
    reference, com_reference, standing, duration = _references(config, spec)
    station = make_station(config.station)
    period = config.station.sensors_config().period
    if spec.mode == "torque":
        control = build_balance_control(
            robot,
            station,
            reference,
            com_reference,
            standing,
            motor_model,
            config.control,
            control_period=period,
            fused=config.fused,
        )
    else:
        control = build_position_control(robot, station, reference)
    builder = DiagramBuilder()
    diagram = builder.AddNamedSystem("control", control.diagram)
    plant = control.station.GetSubsystemByName("plant")
    soles = list(robot.contacts.soles)
    contacts = builder.AddNamedSystem("sole_contacts", SoleContacts(plant, soles))
    builder.Connect(diagram.GetOutputPort("contact_results"), contacts.get_input_port())
    com_source = builder.AddNamedSystem(
        "com_reference_log", TrajectorySource(com_reference)
    )
    wrench = None
    if spec.kind == "push":
        body = plant.GetBodyByName(config.push_body(robot))
        push = builder.AddNamedSystem(
            "push", PushSource(body.index(), config.pushes.point)
        )
        wrench = builder.AddNamedSystem(
            "push_wrench", TrajectorySource(_push_wrench(config, spec))
        )
        builder.Connect(wrench.get_output_port(), push.get_input_port())
        builder.Connect(
            push.get_output_port(), diagram.GetInputPort("applied_spatial_force")
        )
    names = ["state_true", "joint_torque_true", "q_cmd"]
    if spec.mode == "torque":
        names += [
            "tau_estimated",
            "tau_desired",
            "supervisor_mode",
            "supervisor_fault",
            "balance_fault",
            "balance_fault_count",
            "fallback_active",
        ]
    ports = {name: diagram.GetOutputPort(name) for name in names}
    ports["soles"] = contacts.get_output_port()
    ports["com_ref"] = com_source.get_output_port()
    loggers = add_loggers(builder, ports, LOG_PERIOD)
    simulator = Simulator(builder.Build())
    label = f"{spec.mode} control, " + (
        f"CoM {config.com_motion.axis} sinusoid"
        if spec.kind == "com"
        else f"push {spec.direction} {spec.force:g} N"
    )
    run_with_progress(simulator, duration, label, steps=4)
    logs = logs_to_arrays(loggers, simulator.get_context())
    truth = _truth(robot, plant, logs)
    return {"spec": spec, "metrics": _metrics(config, robot, spec, logs, truth)} | (
        {"logs": _kept_logs(logs, truth)} if spec.kind == "com" else {}
    )


def _truth(robot: RobotDescription, plant: MultibodyPlant, logs: dict) -> dict:
    """The true CoM, the soles' poses, the base height and the positions every
    METRIC_STRIDE samples (evaluation only): computed once per run."""
    context = plant.CreateDefaultContext()
    rows = np.arange(0, len(logs["t"]), METRIC_STRIDE)
    nq = plant.num_positions()
    frames = [plant.GetFrameByName(s) for s in robot.contacts.soles]
    base = plant.GetBodyByName(robot.base_body)
    com = np.zeros((len(rows), 3))
    sole_p = np.zeros((len(rows), len(frames), 3))
    sole_z = np.zeros((len(rows), len(frames)))
    base_z = np.zeros(len(rows))
    for k, row in enumerate(rows):
        plant.SetPositions(context, logs["state_true"][row, :nq])
        com[k] = plant.CalcCenterOfMassPositionInWorld(context)
        for s, frame in enumerate(frames):
            X = frame.CalcPoseInWorld(context)
            sole_p[k, s] = X.translation()
            sole_z[k, s] = X.rotation().matrix()[2, 2]
        base_z[k] = base.EvalPoseInWorld(context).translation()[2]
    return {
        "t": logs["t"][rows],
        "rows": rows,
        "com": com,
        "sole_p": sole_p,
        "sole_tilt": np.arccos(np.clip(sole_z, -1.0, 1.0)),
        "base_z": base_z,
        "positions": logs["state_true"][rows, :nq],
    }


def _cop_margins(robot: RobotDescription, soles_log: np.ndarray, sole_poses):
    """Each loaded sole's CoP margin (m; the distance inside its rectangle, negative
    outside), NaN where unloaded: (samples, soles)."""
    names = list(robot.contacts.soles)
    margins = np.full((len(soles_log), len(names)), np.nan)
    for s, name in enumerate(names):
        block = soles_log[:, 5 * s : 5 * s + 5]
        loaded = block[:, 2] > LOADED_SOLE
        X_WS = sole_poses[name]
        R, p = X_WS.rotation().matrix(), X_WS.translation()
        local = (block[:, 3:5] - p[:2]) @ R[:2, :2]
        rectangle = robot.contacts.soles[name]
        margin = np.minimum.reduce(
            [
                local[:, 0] - rectangle.x[0],
                rectangle.x[1] - local[:, 0],
                local[:, 1] - rectangle.y[0],
                rectangle.y[1] - local[:, 1],
            ]
        )
        margins[loaded, s] = margin[loaded]
    return margins


def _metrics(config, robot, spec: RunSpec, logs: dict, truth: dict) -> dict:
    """A run's metrics from its logs and its ground truth (`_truth`)."""
    t = truth["t"]
    rows = truth["rows"]
    start = config.settle
    window = t >= start
    before = np.searchsorted(t, start) - 1
    out: dict = {}
    # The soles and the base against where they were at `settle`.
    slip = np.linalg.norm(truth["sole_p"] - truth["sole_p"][before], axis=2)
    tilt = np.abs(truth["sole_tilt"] - truth["sole_tilt"][before])
    drop = truth["base_z"][before] - truth["base_z"]
    pushes = config.pushes
    out["sole_slip_max_m"] = float(slip[window].max())
    out["sole_tilt_max_rad"] = float(tilt[window].max())
    out["base_drop_max_m"] = float(drop[window].max())
    out["feet_flat"] = bool(
        out["sole_slip_max_m"] < pushes.sole_slip
        and out["sole_tilt_max_rad"] < pushes.sole_tilt
    )
    out["fell"] = bool(out["base_drop_max_m"] >= pushes.fall_drop)
    failures = []
    if not out["feet_flat"]:
        failures.append("a sole lifted or rotated")
    if out["fell"]:
        failures.append("the base dropped")
    soles_log = logs["soles"][rows]
    normal = soles_log[:, 2::5]
    out["peak_normal_force_N"] = np.nanmax(normal[window], axis=0).tolist()
    # (The station's plant orders its positions as the robot's model does.)
    poses = sole_poses(robot, truth["positions"][before])
    margins = _cop_margins(robot, soles_log, poses)
    loaded = margins[window]
    out["cop_margin_min_m"] = (
        float(np.nanmin(loaded)) if np.isfinite(loaded).any() else math.nan
    )
    if spec.mode == "torque":
        mode = logs["supervisor_mode"][:, 0]
        after = logs["t"] >= start
        out["torque_share"] = float(np.mean(mode[after] > 0.999))
        out["fell_back"] = bool(np.any(mode[after] < 0.999))
        bits = np.bitwise_or.reduce(logs["supervisor_fault"][after, 0].astype(int))
        out["supervisor_faults"] = describe_faults(int(bits))
        if out["fell_back"]:
            failures.append(f"fell back to position control ({describe_faults(bits)})")
        out["qp_faults"] = int(logs["balance_fault_count"][-1, 0])
        faults = logs["balance_fault"][:, 0]
        out["qp_fault_kinds"] = sorted(
            BALANCE_FAULTS[int(f)] for f in set(faults[faults > 0].tolist())
        )
    out["failures"] = failures
    out["survived"] = not failures
    com = truth["com"]
    com_ref = logs["com_ref"][rows, :3]
    if spec.kind == "com":
        error = np.linalg.norm(com - com_ref, axis=1)[window]
        axis_error = (com - com_ref)[window, _com_axis(config)]
        out["com_rms_error_m"] = float(np.sqrt(np.mean(error**2)))
        out["com_max_error_m"] = float(error.max())
        out["com_axis_rms_error_m"] = float(np.sqrt(np.mean(axis_error**2)))
        if spec.mode == "torque":
            out["estimation"] = _estimation(robot, config, logs)
    else:
        horizontal = np.linalg.norm((com - com[before])[:, :2], axis=1)
        out["com_excursion_m"] = float(horizontal[window].max())
        out["settle_time_s"] = _settle_time(
            t, horizontal, start + pushes.duration, pushes.settled
        )
    return out


def _settle_time(t, distance, t_end, tolerance) -> float | None:
    """Time from t_end until `distance` stays under `tolerance` (None: never)."""
    outside = np.nonzero((distance > tolerance) & (t >= t_end))[0]
    if len(outside) == 0:
        return 0.0
    last = outside[-1]
    if last + 1 >= len(t):
        return None
    return float(t[last + 1] - t_end)


def _estimation(robot: RobotDescription, config, logs: dict) -> dict:
    """τ̂ on the torque-controlled joints from `settle`, judged as the paper defines
    the estimator (Sec. 2, noncausal: its sample at t describes the robot t_d
    earlier, t_d the chain's estimation delay): "delayed", against τ(t − t_d), each
    joint's RMS error against GOAL_RMS_OVER_PEAK of its peak |τ| (`met`);
    "undelayed", against τ(t), what the controller acts on (its error adds the
    delay's)."""
    joints = resolved(robot, config.control).torque.joints
    columns = [robot.joints.index(j) for j in joints]
    period = config.station.sensors_config().period
    delay = config.control.torque.estimator.delay(period)
    tau_hat = logs["tau_estimated"][:, columns]
    tau = logs["joint_torque_true"][:, columns]
    out = {"joints": joints, "delay_s": delay}
    for key, samples in (("delayed", round(delay / LOG_PERIOD, 9)), ("undelayed", 0)):
        e = errors(logs["t"], tau_hat, tau, samples, config.settle)
        out[key] = {
            "rms_error_Nm": e["rms"].tolist(),
            "peak_torque_Nm": e["peak"].tolist(),
            "rms_over_peak": e["ratio"].tolist(),
        }
    met = np.all(np.array(out["delayed"]["rms_over_peak"]) < GOAL_RMS_OVER_PEAK)
    return out | {"goal": GOAL_RMS_OVER_PEAK, "met": bool(met)}


def _kept_logs(logs: dict, truth: dict) -> dict:
    """What the figures need, every 10 ms: t, the true CoM and its reference, the
    soles' forces and CoPs."""
    keep = slice(None, None, 2)
    return {
        "t": truth["t"][keep],
        "com": truth["com"][keep],
        "com_ref": logs["com_ref"][truth["rows"]][keep, :3],
        "soles": logs["soles"][truth["rows"]][keep],
    }


# ------------------------------------------------------------------ motor model


def identification_configs(robot: RobotDescription) -> list[Path]:
    """The identification configs of the joints the description's own
    identification leaves out: every `identify_*.yaml` of the robot's folder."""
    return sorted(robot.folder.glob("identify_*.yaml"))


def _identify(station_robot: str, config_file: str, out: Path) -> Path:
    from hrp2_drake.assembly.identification import (
        IdentifyConfig,
        identify_motor_model,
    )
    from hrp2_drake.config import load_config

    config = (
        load_config(IdentifyConfig, filename=config_file, validate=False)
        if config_file
        else IdentifyConfig()
    )
    config.station = replace(config.station, robot=station_robot)
    config.validate()
    return identify_motor_model(config, out)


def identify_legs(config: BalanceExperimentConfig, out: Path) -> MotorModel:
    """The controller's motor model of the legs, identified on the simulated robot
    hanging (`hrp2-drake identify`): the description's identification, then each
    `identification_configs` file, in parallel; merged into
    out/motor_model.yaml."""
    robot = config.station.description()
    files = ["", *map(str, identification_configs(robot))]
    console.say(
        f"no --motor-model: identifying the legs first ({len(files)} "
        "identifications, hrp2-drake identify)"
    )
    with ProcessPoolExecutor(
        min(config.workers, len(files)),
        mp_context=get_context("spawn"),
        initializer=console.start_worker,
        initargs=(console.program(), "identify"),
    ) as pool:
        futures = [
            pool.submit(
                _identify,
                config.station.robot,
                name,
                out / (Path(name).stem if name else "identify"),
            )
            for name in files
        ]
        models = [MotorModel.load(f.result()) for f in futures]
    merged = MotorModel.from_joints(
        {j: m.subset([j]) for m in models for j in m.joint_names}
    )
    merged.save(out / "motor_model.yaml")
    return merged


# ------------------------------------------------------------------ the search


def _worker_run(config, motor_model, spec):
    return simulate_run(config, motor_model, spec)


def largest_push(
    config: BalanceExperimentConfig,
    motor_model: MotorModel,
    mode: str,
    direction: str,
) -> dict:
    """Doubles the push from `first` until the robot fails, then bisects to
    `resolution`: the largest push survived and every run's metrics by force."""
    pushes = config.pushes
    runs: dict[float, dict] = {}

    def survives(force: float) -> bool:
        result = simulate_run(
            config, motor_model, RunSpec(mode, "push", direction, force)
        )
        runs[force] = result["metrics"]
        return result["metrics"]["survived"]

    survived, failed = 0.0, None
    force = pushes.first
    while force <= pushes.largest:
        if survives(force):
            survived = force
            force *= 2.0
        else:
            failed = force
            break
    if failed is not None:
        while failed - survived > pushes.resolution:
            middle = 0.5 * (survived + failed)
            if survives(middle):
                survived = middle
            else:
                failed = middle
    return {
        "mode": mode,
        "direction": direction,
        "largest_survived_N": survived,
        "smallest_failed_N": failed,
        "runs": {f"{force:g}": metrics for force, metrics in sorted(runs.items())},
    }


def run_balance(
    config: BalanceExperimentConfig, motor_model: MotorModel, out: Path
) -> dict:
    """Both experiments under both controls; writes balance.md, balance.json and the
    figures into `out`; returns the summary."""
    config.validate()
    robot = config.station.description()
    joints = resolved(robot, config.control).torque.joints
    missing = [j for j in joints if j not in motor_model.joint_names]
    if missing:
        raise ValueError(
            f"balance: the motor model has no joints {missing}, which balance "
            f"torque-controls (it has {motor_model.joint_names})"
        )
    motor_model = motor_model.subset(joints)
    calibration = None
    if config.calibration.enabled:
        calibration = calibrate(
            config.station, config.control.torque.estimator.window, config.calibration
        )
        config = calibrated(config, calibration)
    program = console.program()
    with ProcessPoolExecutor(
        config.workers,
        mp_context=get_context("spawn"),
        initializer=console.start_worker,
        initargs=(program, "balance"),
    ) as pool:
        com_runs = {
            mode: pool.submit(_worker_run, config, motor_model, RunSpec(mode, "com"))
            for mode in MODES
        }
        push_runs = [
            pool.submit(largest_push, config, motor_model, mode, direction)
            for direction in config.pushes.directions
            for mode in MODES
        ]
        com = {mode: future.result() for mode, future in com_runs.items()}
        pushes = [future.result() for future in push_runs]
    summary = {
        "robot": robot.name,
        "controlled_joints": joints,
        "settings": _settings(robot, config),
        "com_motion": {mode: com[mode]["metrics"] for mode in MODES},
        "pushes": pushes,
        "push_comparison": _push_comparison(pushes),
    }
    if calibration is not None:
        summary["calibration"] = calibration
    out.mkdir(parents=True, exist_ok=True)
    (out / "balance.json").write_text(json.dumps(summary, indent=2))
    np.savez_compressed(
        out / "balance_com.npz",
        **{
            f"{mode}_{name}": value
            for mode in MODES
            for name, value in com[mode]["logs"].items()
        },
    )
    _figures(robot, config, com, pushes, out)
    (out / "balance.md").write_text(report_markdown(summary))
    return summary


def calibrated(
    config: BalanceExperimentConfig, calibration: dict
) -> BalanceExperimentConfig:
    """`config` with what the calibration found (`calibrate`): the estimator starts
    with the F/T offsets and subtracts the IMU's, and with `apply_com_offset` torque
    control's CoM reference is moved by the CoM offset."""
    torque = config.control.torque
    estimator = replace(
        torque.estimator,
        offsets=dict(calibration["ft_offsets"]),
        imu_offset=list(calibration["imu_offset"]),
    )
    control = replace(config.control, torque=replace(torque, estimator=estimator))
    if config.calibration.apply_com_offset:
        control = replace(control, com_offset=list(calibration["com_offset_m"]))
    return replace(config, control=control)


def _settings(robot: RobotDescription, config: BalanceExperimentConfig) -> dict:
    """What the run was asked, as its report shows it (`experiments.balance.report`)."""
    motion, pushes = config.com_motion, config.pushes
    return {
        "solver": config.control.balance.solver,
        "com_motion": {
            "axis": motion.axis,
            "amplitude_m": motion.amplitude,
            "period_s": motion.period,
            "duration_s": motion.duration,
        },
        "pushes": {
            "body": config.push_body(robot),
            "directions": list(pushes.directions),
            "duration_s": pushes.duration,
            "first_N": pushes.first,
            "resolution_N": pushes.resolution,
            "sole_slip_m": pushes.sole_slip,
            "sole_tilt_rad": pushes.sole_tilt,
            "fall_drop_m": pushes.fall_drop,
            "settled_m": pushes.settled,
        },
        "estimation_goal": GOAL_RMS_OVER_PEAK,
    }


def _push_comparison(pushes: list[dict]) -> dict:
    """Per direction, the largest push both controls survived and each one's
    metrics there."""
    out = {}
    by = {(p["direction"], p["mode"]): p for p in pushes}
    for direction in {p["direction"] for p in pushes}:
        runs = {m: by[(direction, m)]["runs"] for m in MODES if (direction, m) in by}
        if len(runs) < 2:
            continue
        common = [
            f
            for f in runs["torque"]
            if f in runs["position"]
            and runs["torque"][f]["survived"]
            and runs["position"][f]["survived"]
        ]
        if not common:
            continue
        force = max(common, key=float)
        out[direction] = {"force_N": float(force)} | {
            mode: runs[mode][force] for mode in MODES
        }
    return out


# ------------------------------------------------------------------ the report


def _figures(robot, config, com: dict, pushes: list[dict], out: Path) -> None:
    plt = pyplot()
    fig, (ax_com, ax_cop) = plt.subplots(1, 2, figsize=(12, 4.5))
    axis = _com_axis(config)
    for mode, style in zip(MODES, ("-", "--")):
        logs = com[mode]["logs"]
        ax_com.plot(
            logs["t"], logs["com"][:, axis] * 1e3, style, label=f"{mode} control"
        )
    logs = com["torque"]["logs"]
    ax_com.plot(logs["t"], logs["com_ref"][:, axis] * 1e3, ":k", label="reference")
    ax_com.set_xlabel("t (s)")
    ax_com.set_ylabel(f"CoM {config.com_motion.axis} (mm)")
    ax_com.set_title("CoM: the authors' sinusoid")
    legend_beside(ax_com)
    # The support polygon: each sole's rectangle at its standing pose.
    standing = standing_positions(robot, initial_joint_positions(config.station))
    poses = sole_poses(robot, standing)
    for name, sole in robot.contacts.soles.items():
        X = poses[name]
        corners = np.array([X.multiply(c) for c in sole.corners()[[0, 1, 3, 2, 0]]])
        ax_cop.plot(corners[:, 0] * 1e3, corners[:, 1] * 1e3, "k-", lw=1)
    for mode, style, color in zip(MODES, ("-", "--"), ("C0", "C1")):
        soles = com[mode]["logs"]["soles"]
        window = com[mode]["logs"]["t"] >= config.settle
        for s in range(len(robot.contacts.soles)):
            block = soles[window, 5 * s : 5 * s + 5]
            loaded = block[:, 2] > LOADED_SOLE
            ax_cop.plot(
                block[loaded, 3] * 1e3,
                block[loaded, 4] * 1e3,
                style,
                color=color,
                lw=0.8,
                label=f"{mode} control" if s == 0 else None,
            )
    ax_cop.set_aspect("equal")
    ax_cop.set_xlabel("x (mm)")
    ax_cop.set_ylabel("y (mm)")
    ax_cop.set_title("each sole's CoP in the support polygon")
    legend_beside(ax_cop)
    save_figure(fig, out / "balance_com_cop.png", tight=True)

    fig, axes = plt.subplots(1, max(len(config.pushes.directions), 1), figsize=(12, 4))
    axes = np.atleast_1d(axes)
    for ax, direction in zip(axes, config.pushes.directions):
        for push in pushes:
            if push["direction"] != direction:
                continue
            forces = [float(f) for f in push["runs"]]
            excursion = [r["com_excursion_m"] * 1e3 for r in push["runs"].values()]
            stood = [r["survived"] for r in push["runs"].values()]
            line = ax.plot(forces, excursion, "o", label=f"{push['mode']} control")
            ax.plot(
                [f for f, s in zip(forces, stood) if not s],
                [e for e, s in zip(excursion, stood) if not s],
                "x",
                color=line[0].get_color(),
                ms=10,
            )
        ax.set_xscale("log")
        ax.set_xlabel(f"{direction} push over {config.pushes.duration:g} s (N)")
        ax.set_ylabel("CoM excursion (mm)")
        ax.set_title(f"{direction} pushes (x: the robot failed)")
        legend_beside(ax)
    save_figure(fig, out / "balance_pushes.png", tight=True)


def shortened(config: BalanceExperimentConfig) -> BalanceExperimentConfig:
    """`--quick` (CI): one sinusoid period, one push direction, two forces at most,
    a shorter observation."""
    motion = replace(config.com_motion, duration=config.com_motion.period)
    pushes = replace(
        config.pushes,
        directions=config.pushes.directions[:1],
        largest=2 * config.pushes.first,
        resolution=config.pushes.first,
        observe=1.0,
    )
    return replace(config, com_motion=motion, pushes=pushes)
