"""`hrp2-drake track --robot FILE`: the paper's torque control on any robot described
by a robot description, against its own position servo.

Two runs per controller, from the description alone:

1. **Free-space tracking**: every controlled joint follows a sinusoid around the home
   pose (the other joints hold it), under the robot's position servo, then under the
   paper's torque control (estimation + inverse dynamics + Δq controller, Sec. 4)
   with each K6 of the config. Table: maximum and RMS tracking error per joint, of
   the true joint angles.
2. **Force task at the tool** (fixed-base robots with a `tool_frame` and a
   `force_sensor`): a table is placed under the tool tip at the home pose, and the
   torque controller (K6 of `force_k6`, K_f) presses with a force that ramps to
   `press` then oscillates by ±`amplitude` (the environment's reaction as f_ref, in
   the sensor frame, eq. 12). Ground truth is the contact force on the robot
   (Drake's contact results), for evaluation only.

The motor model is used at the gain the station's servo runs at
(`motor_model_at_station_gain`): a model identified from logs that state the servo's
gain holds at that gain, not necessarily the simulated servo's.

A robot on a servo bus runs at the bus's rate (its `sensors.period`), inside the
simulated loop as on the wire: its sensors sample the bus's read-to-write delay
before each tick (`StationConfig.sample_lead`), its goals are whole encoder pulses,
and position control too gets its goal once per period. Its report adds a table at
other rates (`rates`: 100, 200, 500 Hz and 1 kHz by default): does torque control
still beat the servo's position control at the rate the bus allows?

Writes track.md, track.json and plots. Nothing here knows a robot's names.
"""

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.multibody.plant import ContactResults, MultibodyPlant
from pydrake.multibody.tree import BodyIndex, Frame
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import Context, DiagramBuilder, LeafSystem
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.assembly.builders import (
    JointReference,
    build_position_control,
    build_torque_control,
)
from hrp2_drake.assembly.robot_control import TorqueControlSources
from hrp2_drake.assembly.sinusoid import check_sinusoid, sinusoid_reference
from hrp2_drake.assembly.torque_control import (
    EstimatorSettings,
    TorqueControlConfig,
    at_period,
    check_for_robot,
)
from hrp2_drake.config import check_finite, replace_fields
from hrp2_drake.description import RobotDescription
from hrp2_drake.description.bus import bus_for_period
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.multibody import is_strictly_below, joint_indexing, tree_parents
from hrp2_drake.report import legend_beside, markdown_table, pyplot, save_figure
from hrp2_drake.robot.station import (
    BoxObstacle,
    StationConfig,
    initial_joint_positions,
    make_station,
)
from hrp2_drake.simulation import run_with_progress


@dataclass
class TrackConfig:
    """Configuration of `hrp2-drake track`.

    Args:
        station: the robot (its `robot`, scenario, sensors, servo).
        torque_control: the torque controller (its k6 is replaced by each of `k6`;
            default: the F/T offsets calibrated over [0.2, 0.5) s, while the robot
            holds its home pose and the tool just touches the table), stated at 1
            kHz: on a robot with another period, the same spans of time
            (`at_period`).
        k6: the torque controller's position gains to compare (Sec. 4.2).
        duration: length of the free-space motion (s), after `settle`.
        settle: position control at the home pose before torque control starts (s).
        amplitude: of each controlled joint's sinusoid (rad).
        frequency: of the sinusoids (Hz); joint k is phase-shifted by k/n of a period.
        force_task: run the force task (fixed-base robots with a tool_frame and a
            force_sensor; `hrp2-drake track` turns it off for a fixed robot
            without them unless its --config sets it).
        force_k6: K6 of the force task.
        kf: force gain K_f of the force task.
        press: the mean force of the tool on the table (N).
        force_amplitude: the oscillation of the force around `press` (N).
        force_frequency: its frequency (Hz).
        force_duration: the force task's length after the ramp (s).
        ramp: time to lower the tool onto the table (first half) and ramp the force
            from 0 to `press` (second half) (s).
        gap: height of the tool above the table at home (m).
        rates: for a robot on a bus, the loop rates (Hz) of the rate table: position
            control and torque control at each, the bus's read-to-write delay inside
            the loop (at a rate the described bus cannot carry, the fastest bus its
            servos allow, said in the table); empty: none.
    """

    station: StationConfig = field(
        default_factory=lambda: StationConfig(robot="iiwa14", scenario="fixed_base")
    )
    torque_control: TorqueControlConfig = field(
        default_factory=lambda: TorqueControlConfig(
            estimator=EstimatorSettings(offset_calibration_time=0.3)
        )
    )
    k6: list[float] = field(default_factory=lambda: [1.0, 0.3])
    duration: float = 6.0
    settle: float = 0.6
    amplitude: float = 0.2
    frequency: float = 0.4
    force_task: bool = True
    force_k6: float = 0.3
    kf: float = 1.0
    press: float = 20.0
    force_amplitude: float = 10.0
    force_frequency: float = 0.5
    force_duration: float = 4.0
    ramp: float = 1.0
    gap: float = 0.005
    rates: list[float] = field(default_factory=lambda: [100.0, 200.0, 500.0, 1000.0])

    def period(self) -> float:
        """The control period: the station's sensor period (on a bus, the bus's)."""
        return self.station.sensors_config().period

    def torque_control_at_period(
        self, period: float | None = None
    ) -> TorqueControlConfig:
        """`torque_control` at `period` (default: the robot's; `at_period`)."""
        return at_period(self.torque_control, period or self.period())

    def validate(self) -> None:
        self.station.validate()
        self.torque_control.validate()
        where = "TrackConfig"
        if not self.k6:
            raise ValueError(f"{where}.k6: positive gains, got {self.k6}")
        for k, gain in enumerate(self.k6):
            check_finite(gain, f"{where}.k6[{k}]", 0.0)
        for name in (
            "duration",
            "settle",
            "frequency",
            "force_k6",
            "ramp",
            "force_frequency",
            "force_duration",
        ):
            check_finite(getattr(self, name), f"{where}.{name}", 0.0)
        for name in ("kf", "press", "force_amplitude", "gap"):
            check_finite(getattr(self, name), f"{where}.{name}", 0.0, strict=False)
        robot = self.station.description()
        check_sinusoid(
            robot,
            initial_joint_positions(self.station),
            self.amplitude,
            self.frequency,
            self.settle,
            where,
        )
        control = f"{where}.torque_control"
        check_for_robot(self.torque_control, robot, control)
        if self.force_amplitude > self.press:
            raise ValueError(
                f"{where}.force_amplitude: {self.force_amplitude:g} N around press "
                f"{self.press:g} N: the tool would pull on the table (at most press)"
            )
        for k, rate in enumerate(self.rates):
            check_finite(rate, f"{where}.rates[{k}]", 0.0)
        if self.force_task and robot.base == "fixed" and not can_press(robot):
            raise ValueError(
                f"TrackConfig.force_task: robot '{robot.name}' has no tool_frame and "
                "force_sensor in its description"
            )


def can_press(robot: RobotDescription) -> bool:
    """Whether the force task can run on `robot`: fixed base, with a `tool_frame` and
    a `force_sensor` in its description."""
    return robot.base == "fixed" and bool(robot.tool_frame and robot.force_sensor)


def motor_model_at_station_gain(
    model: MotorModel, station: StationConfig
) -> MotorModel:
    """`model` at the gain the station's servo runs at (`MotorModel.at_gain`,
    `StationConfig.servo_gain_in_use`): a model identified from logs that state the
    servo's gain holds at `model.gain`, the simulated servo runs at its servo file's
    gain unless `StationConfig.servo_gain`. A model without gain is returned as is.

    Raises:
        ValueError: the model holds at a gain and the station's servo states none.
    """
    if not model.gain:
        return model
    gain = station.servo_gain_in_use()
    if gain is None:
        raise ValueError(
            f"the motor model holds at servo gain {model.gain:g}, but the servo file "
            f"of robot '{station.description().name}' states no gain: set "
            "StationConfig.servo_gain"
        )
    return model.at_gain(gain)


class ContactForceOnBodies(LeafSystem):
    """The total contact force on a set of bodies, in the world frame (N): ground
    truth for a force task (evaluation only).

    .. code-block:: text

                         ┌──────────────────────┐
        contact_results ►│ ContactForceOnBodies ├──► force
                         └──────────────────────┘
    """

    def __init__(self, plant: MultibodyPlant, bodies: list[str]):
        super().__init__()
        self._bodies = {plant.GetBodyByName(b).index() for b in bodies}
        self._results = self.DeclareAbstractInputPort(
            "contact_results", AbstractValue.Make(ContactResults())
        )
        self.DeclareVectorOutputPort("force", 3, self._calc)

    def _calc(self, context: Context, output) -> None:
        results = self._results.Eval(context)
        total = np.zeros(3)
        for i in range(results.num_point_pair_contacts()):
            info = results.point_pair_contact_info(i)
            if info.bodyB_index() in self._bodies:
                total += info.contact_force()
            if info.bodyA_index() in self._bodies:
                total -= info.contact_force()
        output.set_value(
            total
        )  # (point contact only: the station has no hydroelastics)


def _tracking_errors(
    robot: RobotDescription, q_index: np.ndarray, signals: dict, start: float
) -> dict:
    """Maximum and RMS of q_ref − q (true) of the controlled joints after `start`;
    `q_index`: the joints' rows in the station's state."""
    t = signals["t"]
    keep = t >= start
    q_true = signals["state_true"][keep][:, q_index]
    error = signals["q_ref"][keep] - q_true
    cols = [robot.joints.index(j) for j in robot.controlled_joints]
    out = {
        "maximum": np.abs(error[:, cols]).max(axis=0).tolist(),
        "rms": np.sqrt(np.mean(error[:, cols] ** 2, axis=0)).tolist(),
    }
    if (
        "tau_estimated" in signals
    ):  # a torque-control run (ground truth: evaluation only)
        tau_error = (
            signals["tau_estimated"][keep] - signals["joint_torque_true"][keep]
        )[:, cols]
        out["tau_rms_error"] = np.sqrt(np.mean(tau_error**2, axis=0)).tolist()
        if "supervisor_mode" in signals:
            out["torque_share"] = float(
                np.mean(signals["supervisor_mode"][keep] >= 1.0)
            )
        else:
            out["torque_share"] = float(np.mean(signals["fallback_active"][keep] < 0.5))
    return out


def _simulate(control, duration: float, label: str, extra_ports=None) -> dict:
    """Simulates a ControlDiagram, logging its outputs (and `extra_ports`)."""
    from hrp2_drake.simulation import add_loggers, logs_to_arrays

    builder = DiagramBuilder()
    diagram = builder.AddNamedSystem("control", control.diagram)
    ports = {
        name: diagram.GetOutputPort(name) for name in ("q_ref", "state_true", "q_cmd")
    }
    for name in control.output_names():
        if name.startswith(("external_wrench_", "wrench_")) or name in (
            "tau_estimated",
            "joint_torque_true",
            "supervisor_mode",
            "fallback_active",
        ):
            ports[name] = diagram.GetOutputPort(name)
    if extra_ports:
        ports |= extra_ports(builder, diagram)
    loggers = add_loggers(builder, ports, 0.001)
    simulator = Simulator(builder.Build())
    run_with_progress(simulator, duration, label)
    return logs_to_arrays(loggers, simulator.get_context())


#: The plant's step of a robot on a bus (s): `track_station`.
BUS_TIME_STEP = 0.00025


def track_station(
    config: TrackConfig,
    period: float | None = None,
    robot: RobotDescription | None = None,
) -> StationConfig:
    """The station of a run at `period` (s; default: the robot's): a robot on a bus
    (its description, or `robot`'s bus) samples its sensors the bus's
    read-to-write delay before each tick, on a plant of step `BUS_TIME_STEP`."""
    station = config.station
    robot = robot or station.description()
    period = period or config.period()
    if period != config.period():
        station = replace(
            station, sensors=replace(station.sensors_config(), period=period)
        )
    if robot.bus.active:
        # A plant step fine enough to put the bus's sub-millisecond read-to-write
        # delay inside a 1 kHz period (the delay is rounded up to whole steps).
        station = replace(
            station,
            time_step=min(station.time_step, BUS_TIME_STEP),
            sample_lead=robot.bus.timing().read_to_write,
        )
    return station


def run_tracking(
    config: TrackConfig,
    motor_model: MotorModel,
    period: float | None = None,
    robot: RobotDescription | None = None,
) -> dict:
    """Free-space tracking: position control, then torque control at each K6; at
    `period` (s; default: the robot's) with `robot`'s bus (default: the
    description's)."""
    robot = robot or config.station.description()
    period = period or config.period()
    station = track_station(config, period, robot)
    q0 = initial_joint_positions(station)
    reference = sinusoid_reference(
        robot, q0, config.amplitude, config.frequency, config.settle, config.duration
    )
    duration = reference.end_time()
    runs = {}
    command_period = period if robot.bus.active else 0.0
    position = build_position_control(
        robot, make_station(station), reference, command_period
    )
    q_index = joint_indexing(
        position.station.GetSubsystemByName("plant"), robot.joints
    ).q
    signals = _simulate(position, duration, "position control")
    runs["position control"] = _tracking_errors(robot, q_index, signals, config.settle)
    torque = replace(config.torque_control_at_period(period), start_time=config.settle)
    for k6 in config.k6:
        control = build_torque_control(
            robot,
            make_station(station),
            reference,
            motor_model,
            replace_fields(torque, {"controller.k6": k6}),
            control_period=period,
        )
        signals = _simulate(control, duration, f"torque control K6={k6:g}")
        runs[f"torque control K6={k6:g}"] = _tracking_errors(
            robot, q_index, signals, config.settle
        )
    return runs


def run_rates(config: TrackConfig, motor_model: MotorModel) -> list[dict]:
    """The rate table of a robot on a bus: tracking at each of `config.rates`, on the
    described bus where it carries the rate, else on the fastest its servos allow."""
    robot = config.station.description()
    rows = []
    for rate in config.rates:
        period = 1.0 / rate
        try:
            bus, note = bus_for_period(robot.bus, period)
        except ValueError as error:
            rows.append({"rate": rate, "skipped": str(error)})
            continue
        at_rate = replace(robot, bus=bus, sensors=replace(robot.sensors, period=period))
        runs = run_tracking(config, motor_model, period, at_rate)
        rows.append(
            {
                "rate": rate,
                "note": note,
                "read_to_write_ms": bus.timing().read_to_write * 1e3,
                "cycle_ms": bus.timing().cycle * 1e3,
                "runs": runs,
            }
        )
    return rows


def run_force_task(config: TrackConfig, motor_model: MotorModel, out: Path) -> dict:
    """The force task at the tool on a table (module docstring)."""
    robot = config.station.description()
    q0 = initial_joint_positions(config.station)
    # The tool tip's pose at home (the tip frame is the centre of its contact sphere).
    plant = robot.make_plant()
    context = plant.CreateDefaultContext()
    x = plant.GetPositions(context)
    x[joint_indexing(plant, robot.joints).q] = q0
    plant.SetPositions(context, x)
    tip = plant.GetFrameByName(robot.tool_frame)
    station = _with_table_below(config, tip, tip.CalcPoseInWorld(context).translation())
    # f_ref: the table's reaction on the tool, in the sensor frame at home.
    sensor = robot.force_torque_sensors[robot.force_sensor]
    R_WS = (
        plant.GetFrameByName(sensor.frame).CalcPoseInWorld(context).rotation().matrix()
    )
    up_S = R_WS.T @ np.array([0.0, 0.0, 1.0])
    t, magnitude, force_reference = _force_reference(config, up_S)
    reference = _lowering(plant, context, robot, tip, q0, config, t[-1])
    torque = replace_fields(
        config.torque_control,
        {
            "controller.k6": config.force_k6,
            "controller.kf": [config.kf],
            "controller.force_frame": sensor.frame,
            "start_time": config.settle,
        },
    )
    control = build_torque_control(
        robot,
        make_station(station),
        reference,
        motor_model,
        torque,
        control_period=station.sensors_config().period,
        force_reference=force_reference,
    )
    tool_bodies = _bodies_below(
        robot, plant, robot.sensor_body(robot.force_sensor, plant)
    )
    signals = _simulate(
        control, t[-1], "force task", _contact_force_on(control, tool_bodies)
    )
    time = signals["t"]
    desired = np.interp(time, t, magnitude)
    achieved = signals["contact_force"][:, 2]  # the table pushes up on the tool
    estimate = signals[f"external_wrench_{robot.force_sensor}"][:, 3:] @ up_S
    result = _force_errors(config, time, desired, achieved, estimate)
    _plot_force(time, desired, achieved, estimate, config, out / "track_force.png")
    return result


def _with_table_below(
    config: TrackConfig, tip: Frame, p_tip: np.ndarray
) -> StationConfig:
    """The station with a table `gap` below the tool at home, so that nothing touches
    while the F/T offsets are calibrated; the joint reference then lowers the tool
    onto it (a reference compatible with the contact, as in the paper's Sec. 5.4)."""
    top = _lowest_collision_point(config.station, tip.body().name()) - config.gap
    return replace(
        config.station,
        obstacles=[
            BoxObstacle(
                "table", [0.4, 0.4, 0.05], [p_tip[0], p_tip[1], top - 0.025, 0, 0, 0]
            )
        ],
    )


def _force_reference(
    config: TrackConfig, up_S: np.ndarray
) -> tuple[np.ndarray, np.ndarray, PiecewisePolynomial]:
    """The force task's sample times (s), the desired push's magnitude (N) at them,
    and f_ref: that push along `up_S` (the sensor frame's up at home)."""
    t = np.arange(0.0, config.settle + config.ramp + config.force_duration + 1e-9, 0.01)
    half = config.ramp / 2  # first half: lower the tool; second half: ramp the force
    s = np.clip((t - config.settle - half) / half, 0.0, 1.0)
    magnitude = config.press * s * s * (3 - 2 * s)
    after = np.clip(t - config.settle - config.ramp, 0.0, None)
    magnitude += config.force_amplitude * np.sin(
        2 * np.pi * config.force_frequency * after
    )
    f_ref = np.zeros((6, len(t)))
    f_ref[3:] = np.outer(up_S, magnitude)
    return t, magnitude, PiecewisePolynomial.FirstOrderHold(t, f_ref)


def _contact_force_on(control, tool_bodies: list[str]):
    """`_simulate`'s extra port: the contact force on the tool's bodies (N, world),
    the truth the force task is measured against."""

    def truth(builder, diagram):
        station_plant = control.station.GetSubsystemByName("plant")
        system = builder.AddNamedSystem(
            "contact_force", ContactForceOnBodies(station_plant, tool_bodies)
        )
        builder.Connect(
            diagram.GetOutputPort("contact_results"), system.get_input_port()
        )
        return {"contact_force": system.get_output_port()}

    return truth


def _force_errors(
    config: TrackConfig,
    time: np.ndarray,
    desired: np.ndarray,
    achieved: np.ndarray,
    estimate: np.ndarray,
) -> dict:
    """The force task's errors (N) once the force is ramped up: the achieved force
    against the desired one, and the F/T estimate against the achieved force."""
    window = time >= config.settle + config.ramp
    error = achieved[window] - desired[window]
    return {
        "press_N": config.press,
        "amplitude_N": config.force_amplitude,
        "rms_error_N": float(np.sqrt(np.mean(error**2))),
        "max_error_N": float(np.abs(error).max()),
        "mean_error_N": float(error.mean()),
        "estimate_rms_error_N": float(
            np.sqrt(np.mean((estimate[window] - achieved[window]) ** 2))
        ),
        "amplitude_ratio": float(
            np.ptp(achieved[window]) / max(np.ptp(desired[window]), 1e-9)
        ),
    }


def _lowering(
    plant, context, robot, tip, q0, config: TrackConfig, end: float
) -> JointReference:
    """Home, then the controlled joints move the tool tip straight down by `gap` over
    the first half of the ramp (Δq = J⁺ Δx on the tip's translational Jacobian)."""
    from pydrake.multibody.tree import JacobianWrtVariable

    J = plant.CalcJacobianTranslationalVelocity(
        context,
        JacobianWrtVariable.kV,
        tip,
        np.zeros(3),
        plant.world_frame(),
        plant.world_frame(),
    )
    indexing = joint_indexing(plant, robot.joints)
    cols = [robot.joints.index(j) for j in robot.controlled_joints]
    dq = np.zeros(len(robot.joints))
    dq[cols] = np.linalg.pinv(J[:, indexing.v[cols]]) @ np.array(
        [0.0, 0.0, -config.gap]
    )
    t = np.arange(0.0, end + 1e-9, 0.001)
    half = config.ramp / 2
    x = np.clip((t - config.settle) / half, 0.0, 1.0)
    e = x**3 * (10 - 15 * x + 6 * x**2)
    de = 30 * x**2 * (1 - x) ** 2 / half
    dde = 60 * x * (1 - x) * (1 - 2 * x) / half**2
    return JointReference.from_samples(
        t, q0 + np.outer(e, dq), np.outer(de, dq), np.outer(dde, dq)
    )


def _lowest_collision_point(station_config: StationConfig, body_name: str) -> float:
    """World height (m) of the lowest point of `body_name`'s collision spheres at the
    station's initial pose."""
    from pydrake.geometry import Sphere

    station = make_station(station_config)
    plant = station.GetSubsystemByName("plant")
    scene_graph = station.GetSubsystemByName("scene_graph")
    context = station.CreateDefaultContext()
    query = scene_graph.get_query_output_port().Eval(
        scene_graph.GetMyContextFromRoot(context)
    )
    inspector = query.inspector()
    body = plant.GetBodyByName(body_name)
    heights = [
        query.GetPoseInWorld(g).translation()[2] - inspector.GetShape(g).radius()
        for g in plant.GetCollisionGeometriesForBody(body)
        if isinstance(inspector.GetShape(g), Sphere)
        and inspector.GetProximityProperties(g) is not None
    ]
    if not heights:
        raise ValueError(
            f"tool_frame: its body '{body_name}' has no collision sphere to press with"
        )
    return min(heights)


def _bodies_below(
    robot: RobotDescription, plant: MultibodyPlant, body: str
) -> list[str]:
    """`body` and every body beyond it, away from the base (the tool)."""
    top = int(plant.GetBodyByName(body).index())
    parents = tree_parents(plant, plant.GetBodyByName(robot.base_body).index())
    return [
        plant.get_body(BodyIndex(b)).name()
        for b in parents
        if b == top or is_strictly_below(parents, b, top)
    ]


def _plot_force(
    t, desired, achieved, estimate, config: TrackConfig, path: Path
) -> None:
    fig, ax = pyplot().subplots(figsize=(9, 3.5))
    ax.plot(t, desired, "k--", lw=1, label="reference")
    ax.plot(t, achieved, lw=1.5, label="contact force (truth)")
    ax.plot(t, estimate, lw=0.8, alpha=0.8, label="estimate f̂ (F/T, compensated)")
    ax.axvline(config.settle, color="0.7", lw=0.8)
    ax.set_xlabel("t (s)")
    ax.set_ylabel("force on the table (N)")
    legend_beside(ax)
    save_figure(fig, path, dpi=100, tight=True)


def run_track(
    config: TrackConfig,
    motor_model: MotorModel,
    out: Path,
    sources: TorqueControlSources | None = None,
) -> dict:
    """The whole `hrp2-drake track`: tracking, the force task, report and plots.
    `config` is validated where it was loaded (`validate_config`); `sources`: where
    its torque-control settings came from (`load_on_robot`; None: `config` as the
    caller made it), for the report."""
    robot = config.station.description()
    sources = sources or TorqueControlSources()
    out.mkdir(parents=True, exist_ok=True)
    # The one place where track reads the motor model: at the station's servo gain.
    motor_model = motor_model_at_station_gain(motor_model, config.station)
    summary = {
        "robot": robot.name,
        "joints": list(robot.controlled_joints),
        "motor_model_gain": motor_model.gain,
        "torque_control_from": sources.summary(),
    }
    summary["tracking"] = run_tracking(config, motor_model)
    if robot.bus.active:
        summary["bus"] = {
            "rate": 1.0 / config.period(),
            "read_to_write_ms": robot.bus.timing().read_to_write * 1e3,
        }
        if config.rates:
            summary["rates"] = run_rates(config, motor_model)
    if config.force_task and can_press(robot):
        summary["force_task"] = run_force_task(config, motor_model, out)
    (out / "track.json").write_text(json.dumps(summary, indent=2))
    _plot_tracking(robot, summary["tracking"], out / "track_errors.png")
    (out / "track.md").write_text(_markdown(robot, config, summary, sources))
    return summary


def _plot_tracking(robot: RobotDescription, runs: dict, path: Path) -> None:
    labels = robot.labels()
    x = np.arange(len(labels))
    width = 0.8 / len(runs)
    fig, ax = pyplot().subplots(figsize=(9, 3.5))
    for k, (name, errors) in enumerate(runs.items()):
        ax.bar(x + k * width, np.array(errors["maximum"]) * 1e3, width, label=name)
    ax.set_xticks(x + 0.4 - width / 2, labels)
    ax.set_ylabel("maximum tracking error (mrad)")
    legend_beside(ax)
    save_figure(fig, path, dpi=100, tight=True)


def _markdown(
    robot: RobotDescription,
    config: TrackConfig,
    summary: dict,
    sources: TorqueControlSources,
) -> str:
    labels = robot.labels()
    spread = len(robot.controlled_joints) > 1
    phases = " (phases spread over the joints)" if spread else ""
    gain = summary.get("motor_model_gain")
    model = f" The motor model at servo gain {gain:g}." if gain else ""
    lines = [
        f"# Torque control of {robot.name} against its position servo",
        "",
        f"Every controlled joint follows a sinusoid of {config.amplitude} rad at "
        f"{config.frequency} Hz around the home pose for {config.duration} s{phases}, "
        "after a settle at home. Errors of the true joint angles (mrad), from the end "
        f"of the settle. Plot: `track_errors.png`.{model}",
        "",
        sources.markdown(config.torque_control),
        "",
    ]
    rows = [
        [
            name,
            *(f"{m * 1e3:.2f} ({r * 1e3:.2f})" for m, r in zip(e["maximum"], e["rms"])),
        ]
        for name, e in summary["tracking"].items()
    ]
    lines += markdown_table(["controller", *labels], rows)
    lines += ["", "Cells: maximum (RMS)."]
    if "bus" in summary:
        lines += ["", *_rates_markdown(robot, summary)]
    force = summary.get("force_task")
    if force:
        lines += [
            "",
            "## Force task at the tool",
            "",
            f"The tool presses on a table under its tip: {force['press_N']:g} N "
            f"± {force['amplitude_N']:g} N at {config.force_frequency} Hz, K6 = "
            f"{config.force_k6}, K_f = {config.kf}. Truth: the contact force from "
            "Drake's contact results (evaluation only). Plot: `track_force.png`.",
            "",
            *markdown_table(
                [
                    "RMS error (N)",
                    "maximum error (N)",
                    "mean error (N)",
                    "amplitude ratio",
                    "estimate f̂ vs truth, RMS (N)",
                ],
                [
                    [
                        f"{force['rms_error_N']:.2f}",
                        f"{force['max_error_N']:.2f}",
                        f"{force['mean_error_N']:+.2f}",
                        f"{force['amplitude_ratio']:.2f}",
                        f"{force['estimate_rms_error_N']:.2f}",
                    ]
                ],
                align="rrrrr",
            ),
        ]
    return "\n".join(lines) + "\n"


def _rates_markdown(robot: RobotDescription, summary: dict) -> list[str]:
    """The bus's rate and, per rate of the rate table, position against torque
    control (the better K6), and whether torque control beats the servo."""
    bus = robot.bus
    lines = [
        "## On the bus",
        "",
        f"{len(bus.ids)} {bus.model} at {bus.baud / 1e6:g} Mbit/s: the loop runs at "
        f"{summary['bus']['rate']:.0f} Hz, the command reaching the servos "
        f"{summary['bus']['read_to_write_ms']:.2f} ms after they sampled (the bus's "
        "read-to-write delay, inside the simulated loop: sensors sampled that long "
        "before each tick); goals in whole encoder pulses, position control's goal "
        "written once per period too.",
    ]
    rates = summary.get("rates")
    if not rates:
        return lines
    labels = robot.labels()
    rows = []
    for row in rates:
        if "skipped" in row:
            rows.append([f"{row['rate']:.0f}", "-", "-", "-", "-", "-", row["skipped"]])
            continue
        runs = row["runs"]
        position = runs["position control"]
        torque = {name: e for name, e in runs.items() if name != "position control"}
        best = min(torque, key=lambda name: max(torque[name]["maximum"]))
        beats = all(t <= p for t, p in zip(torque[best]["rms"], position["rms"]))
        chosen = torque[best]
        rows.append(
            [
                f"{row['rate']:.0f}",
                f"{row['read_to_write_ms']:.2f}",
                ", ".join(
                    f"{m * 1e3:.1f} ({r * 1e3:.1f})"
                    for m, r in zip(position["maximum"], position["rms"])
                ),
                f"{best.removeprefix('torque control ')}: "
                + ", ".join(
                    f"{m * 1e3:.1f} ({r * 1e3:.1f})"
                    for m, r in zip(chosen["maximum"], chosen["rms"])
                ),
                f"{chosen['torque_share'] * 100:.0f}%",
                ", ".join(f"{e * 1e3:.0f}" for e in chosen["tau_rms_error"]),
                ("yes" if beats else "no")
                + (f"; {row['note']}" if row["note"] else ""),
            ]
        )
    return lines + [
        "",
        f"**The same motion at other loop rates** (maximum (RMS) error, mrad, "
        f"{', '.join(labels)}): does torque control beat the servo's position control "
        "(RMS, every joint)?",
        "",
        *markdown_table(
            [
                "rate (Hz)",
                "read → write (ms)",
                "position control",
                "torque control (best K6)",
                "in torque control",
                "τ̂ error, RMS (mN·m)",
                "torque control better",
            ],
            rows,
            align="rrllrrl",
        ),
        "",
        "In torque control: the share of the run after the settle with the supervisor "
        "in torque control (the rest: its ramps and fallbacks to position control). "
        "τ̂ error: the estimator's torque against the plant's (ground truth, evaluation "
        "only).",
    ]
