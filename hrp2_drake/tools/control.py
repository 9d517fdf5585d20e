"""`hrp2-drake control --lcm URL | --port DEV` and `hrp2-drake sim-robot --lcm URL`:
the torque controller against a robot in real time, over LCM or on its Dynamixel bus,
and the simulated robot that stands in for a real one behind the LCM channels
(hrp2_drake/hardware).

`control` runs the fused controller (`control/fused.py`, the same steps as the
simulation's systems) in the control loop (`hardware/control_loop.py`), one loop for
both links: over LCM the robot's encoder message is the clock (decode, one tick,
publish); on a bus, the loop's own clock at the bus's period (one sync read, one
tick, one sync write). It starts from the robot's measured pose with a smooth move to
the home pose, times every tick and writes control.md (with a latency histogram),
control.json and control.npz. With `motion: balance` the controller is the balance
experiment's (the whole-body QP over the Δq chain of the legs) on a robot standing on
its soles, its CoM reference and joint reference computed here, on the controller's
side, and fed at each tick (docs/lcm.md, "Balance over LCM"); a robot whose soles do
not carry it when torque control would start is refused (`standing_check`).
`sim-robot` is `RobotBridge`: the simulated station
behind the LCM channels, in real time, with a command watchdog; on exit it writes its
ground truth for evaluation. Start-up order: the robot (or `sim-robot`, or
`sim-servo`) first, then `control`, which waits for the robot.
"""

import json
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.assembly.balance import (
    BalanceControlConfig,
    balance_chain_parts,
    offset_com_reference,
    resolved,
    robot_model,
    standing_com,
    standing_references,
)
from hrp2_drake.assembly.builders import (
    JointReference,
    torque_chain_parts,
)
from hrp2_drake.assembly.robot_control import TorqueControlSources
from hrp2_drake.assembly.sinusoid import check_sinusoid, sinusoid_reference
from hrp2_drake.assembly.torque_control import (
    EstimatorSettings,
    TorqueControlConfig,
    at_period,
    check_for_robot,
)
from hrp2_drake.config import check_finite, moved_keys
from hrp2_drake.console import say
from hrp2_drake.control.balance_reference import ComSinusoid
from hrp2_drake.control.fused import FusedController
from hrp2_drake.control.safety import SafetyConfig
from hrp2_drake.control.torque_chain import TorqueChainParts
from hrp2_drake.description import RobotDescription, load_robot_description
from hrp2_drake.hardware.control_loop import ControlLoop, LoopSettings
from hrp2_drake.hardware.lcm_station import LcmChannels
from hrp2_drake.hardware.link import RobotLink
from hrp2_drake.hardware.robot_bridge import BridgeConfig, RobotBridge
from hrp2_drake.hardware.transport import open_transport
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.report import legend_beside, markdown_table, pyplot, save_figure
from hrp2_drake.robot.station import StationConfig, standing_positions

#: The motions of `hrp2-drake control`.
MOTIONS = ("sinusoid", "hold", "balance")


def _balance_defaults() -> BalanceControlConfig:
    """The balance experiment's control (`BalanceControlConfig`), with the
    staleness limits widened as `torque_control`'s are for a transport's jitter."""
    config = BalanceControlConfig()
    supervisor = replace(config.torque.supervisor, stale_time=0.010, stale_samples=12)
    return replace(config, torque=replace(config.torque, supervisor=supervisor))


@moved_keys(
    station="robot",
    wait_timeout="loop.wait_timeout",
    silence_timeout="loop.silence_timeout",
    ramp_time="loop.ramp_time",
    real_time="loop.real_time",
)
@dataclass
class ControlConfig:
    """Configuration of `hrp2-drake control`.

    Args:
        robot: the robot's description: a robot.yaml path, or the name of a robot in
            models/ ("hrp2", "iiwa14"); empty: HRP-2. It gives the control period
            (its sensors.period: on a bus, the bus's) and the home pose the reference
            goes to (its initial_positions, or its trajectory's first sample).
        torque_control: the controller (its supervisor included; staleness limits
            widened for a transport's jitter), stated at 1 kHz: on a robot with
            another period, the same spans of time (`at_period`).
        duration: how long to run (s of robot time).
        motion: "sinusoid" (every controlled joint around the home pose, `track`'s
            reference), "hold" (the home pose), or "balance" (a robot standing on
            its soles, `balance`'s controller: the CoM follows `com_motion` from
            `settle`, the joints the inverse kinematics' poses, the soles where
            they stand at the home pose).
        amplitude, frequency, settle: the sinusoids (rad, Hz) after `settle` s.
        balance: the controller of `motion: balance` (the whole-body QP over the Δq
            chain of the legs, `hrp2-drake balance`'s; `torque_control` is then
            unused): its `com_offset` and its estimator's `offsets` and
            `imu_offset` are what a calibration found (`hrp2-drake balance`
            writes them in balance.json); staleness limits widened as
            `torque_control`'s.
        com_motion: the CoM motion of `motion: balance`.
        loop: the message-driven loop's own settings: how long to wait for the
            robot's first messages, when the robot is silent (the loop then ramps to
            position control and stops), the ramp that ends every run, real time.
        channels: the LCM channels (over LCM).
        approach_speed: the move from the measured pose to the home pose that starts
            every run, in position control: its fastest joint (rad/s).
    """

    robot: str = ""
    torque_control: TorqueControlConfig = field(
        default_factory=lambda: TorqueControlConfig(
            start_time=0.5,
            estimator=EstimatorSettings(window=41),
            # A sample may come a few ms late over a network (and two real-time
            # processes share 2 cores here): stale after 10 ms or 12 repeated samples,
            # not 2.5 / 5.
            supervisor=SafetyConfig(stale_time=0.010, stale_samples=12),
        )
    )
    duration: float = 5.0
    motion: str = "sinusoid"
    amplitude: float = 0.2
    frequency: float = 0.4
    settle: float = 0.5
    balance: BalanceControlConfig = field(default_factory=_balance_defaults)
    com_motion: ComSinusoid = field(default_factory=ComSinusoid)
    loop: LoopSettings = field(default_factory=LoopSettings)
    channels: LcmChannels = field(default_factory=LcmChannels)
    approach_speed: float = 0.5

    def description(self) -> RobotDescription:
        """The robot's description (checked against its model; cached)."""
        return load_robot_description(self.robot or None)

    def period(self) -> float:
        """The control period: the robot's sensor period (s)."""
        return self.description().sensors.period

    def home(self) -> np.ndarray:
        """The home pose (rad, the description's joint order)."""
        return self.description().home_positions()

    def torque_control_at_period(self) -> TorqueControlConfig:
        """`torque_control` at the robot's period (`at_period`)."""
        return at_period(self.torque_control, self.period())

    def validate(self) -> None:
        """Raises ValueError naming the bad field: the robot, the controller (its gains
        against the robot's joints), the motion against the joints' limits, the loop's
        timing."""
        robot = self.description()
        self.torque_control.validate()
        where = "ControlConfig"
        check_for_robot(self.torque_control, robot, f"{where}.torque_control")
        if self.motion not in MOTIONS:
            raise ValueError(
                f"{where}.motion: '{self.motion}', expected one of {', '.join(MOTIONS)}"
            )
        self.balance.validate()
        self.com_motion.validate(f"{where}.com_motion")
        if self.motion == "balance":
            self._validate_balance(robot, where)
        check_sinusoid(
            robot, self.home(), self.amplitude, self.frequency, self.settle, where
        )
        check_finite(self.duration, f"{where}.duration", 0.0)
        if self.torque_control.start_time >= self.duration:
            raise ValueError(
                f"{where}.torque_control.start_time: {self.torque_control.start_time:g}"
                f" s, not before the run's end (duration {self.duration:g} s): torque "
                "control would never start"
            )
        check_finite(self.approach_speed, f"{where}.approach_speed", 0.0)
        self.loop.validate(self.period(), f"{where}.loop")

    def _validate_balance(self, robot: RobotDescription, where: str) -> None:
        """`motion: balance`: a floating robot with soles, torque control before the
        CoM motion and the motion before the run's end."""
        try:
            robot_model(robot)
        except ValueError as error:
            raise ValueError(f"{where}.motion: {error}") from None
        start = self.balance.torque.start_time
        if not start <= self.settle < self.duration:
            raise ValueError(
                f"{where}.settle: the CoM motion starts at {self.settle:g} s, "
                f"expected after torque control starts (balance.torque.start_time "
                f"{start:g} s) and before the run's end ({self.duration:g} s)"
            )

    def controlled_joints(self) -> list[str]:
        """The joints the run torque-controls: with `motion: balance` the legs
        (`balance.torque.joints`, or the joints between the base and the soles),
        else `torque_control`'s."""
        if self.motion == "balance":
            return list(self.balance_at_period().torque.joints)
        return self.torque_control.controlled_joints(self.description())

    def balance_at_period(self) -> BalanceControlConfig:
        """`balance` for the robot at its period: its Δq chain `at_period`, its
        joints filled in (`assembly.balance.resolved`)."""
        config = replace(
            self.balance, torque=at_period(self.balance.torque, self.period())
        )
        return resolved(self.description(), config)


def at_robot_gain(motor_model: MotorModel, robot: RobotDescription) -> MotorModel:
    """`motor_model` at the servo gain `robot` runs at (its `position_loop.gain`;
    unset, or a model stated at no gain: as it is)."""
    return motor_model.at_gain(robot.position_loop.gain or motor_model.gain)


def control_chain_parts(
    config: ControlConfig,
    motor_model: MotorModel,
    reference: JointReference | None = None,
) -> TorqueChainParts:
    """The controller's chain for `config`'s motion: the balance QP over the Δq
    chain of the legs with `motion: balance`, else the torque-control chain; built
    for the reference from home, `reference` if given (`control_references`; the
    parts read only its start)."""
    robot = config.description()
    if reference is None:
        reference, _ = control_references(config)
    if config.motion != "balance":
        return torque_chain_parts(
            robot,
            reference,
            motor_model,
            config.torque_control_at_period(),
            period=config.period(),
        )
    balance = config.balance_at_period()
    missing = [j for j in balance.torque.joints if j not in motor_model.joint_names]
    if missing:
        raise ValueError(
            f"motion balance: the motor model has no joints {missing}, which balance "
            f"torque-controls (it has {motor_model.joint_names})"
        )
    standing = standing_positions(robot, config.home())
    return balance_chain_parts(
        robot,
        reference,
        standing,
        motor_model.subset(balance.torque.joints),
        balance,
        period=config.period(),
    )


def control_references(
    config: ControlConfig, start: np.ndarray | None = None
) -> tuple[JointReference, PiecewisePolynomial | None]:
    """The run's references, computed on the controller's side as a robot's
    controller does: the joints' (`control_reference`) and, with `motion: balance`,
    the CoM's (9 rows: what the QP tracks, moved by `balance.com_offset`; None
    without balance); both after the move from `start` if given (`approached`)."""
    if config.motion != "balance":
        return control_reference(config, start), None
    robot = config.description()
    standing = standing_positions(robot, config.home())
    t = np.arange(0.0, config.duration + 1.0 + 0.0105, 0.01)
    com = config.com_motion.samples(standing_com(robot, standing), t, config.settle)
    reference, com_reference = standing_references(robot, standing, t, com)
    com_reference = offset_com_reference(com_reference, config.balance.com_offset)
    if start is None:
        return reference, com_reference
    return approached(config, reference, com_reference, start)


def approached(
    config: ControlConfig,
    reference: JointReference,
    com_reference: PiecewisePolynomial | None,
    start: np.ndarray,
) -> tuple[JointReference, PiecewisePolynomial | None]:
    """The references from home (`control_references(config)`) delayed by a smooth
    move from `start` (the measured pose, rad) to their first pose
    (`JointReference.after_approach`), the CoM's held meanwhile: what the run
    follows once connected (the references, the inverse kinematics included, are
    computed before: the robot's first sample waits for nothing but the tick)."""
    reference = reference.after_approach(start, config.approach_speed)
    if com_reference is not None and reference.approach_time:
        com_reference = com_reference.Clone()
        com_reference.shiftRight(reference.approach_time)  # held before it
    return reference, com_reference


#: A balance run starts only if its soles' F/T sensors carry this share of the
#: robot's weight.
STANDING_SHARE = 0.5


def standing_check(robot: RobotDescription, controller: FusedController):
    """`ControlLoop`'s check before torque control starts (its `start_check`) with
    `motion: balance`: the robot stands on its soles, the F/T sensors on them
    carrying at least STANDING_SHARE of its weight (the norms of their forces,
    biases and all); a robot hanging, lifted or lying gets no torque command from a
    QP that believes it stands. Returns the check: a sentence if it fails."""
    plant = robot_model(robot)
    context = plant.CreateDefaultContext()
    weight = plant.CalcTotalMass(context) * np.linalg.norm(
        plant.gravity_field().gravity_vector()
    )
    rows = controller.layout.signals()
    sensors = [
        name
        for name in robot.sensor_names()
        if any(
            plant.GetBodyByName(robot.sensor_body(name, plant)).index()
            in {b.index() for b in plant.GetBodiesWeldedTo(sole.body())}
            | {sole.body().index()}
            for sole in map(plant.GetFrameByName, robot.contacts.soles)
        )
    ]
    forces = [controller.sensor_buffer[rows[f"wrench_{name}"]][3:] for name in sensors]

    def check() -> str:
        carried = sum(float(np.linalg.norm(force)) for force in forces)
        if carried >= STANDING_SHARE * weight:
            return ""
        where = ", ".join(sensors) or "none of its F/T sensors is on a sole"
        return (
            f"motion balance: the soles' F/T sensors ({where}) carry {carried:.0f} N "
            f"of the robot's {weight:.0f} N: it is not standing on its soles (sim-robot"
            " --scenario standing); torque control did not start"
        )

    return check


def control_reference(
    config: ControlConfig, start: np.ndarray | None = None
) -> JointReference:
    """The run's joint reference: home for `settle` s, then `motion`; after a move
    from `start` (the measured pose) to home if given
    (`JointReference.after_approach`). With `motion: balance`, the inverse
    kinematics' poses (`control_references`)."""
    if config.motion == "balance":
        return control_references(config, start)[0]
    robot = config.description()
    q0 = config.home()
    if config.motion == "hold":
        reference = JointReference.hold(q0, config.duration + 1.0)
    else:
        reference = sinusoid_reference(
            robot,
            q0,
            config.amplitude,
            config.frequency,
            config.settle,
            config.duration + 1.0 - config.settle,
        )
    if start is None:
        return reference
    return reference.after_approach(start, config.approach_speed)


def open_link(
    config: ControlConfig,
    controller: FusedController,
    lcm_url: str = "",
    port: str = "",
    lockstep: bool = False,
) -> RobotLink:
    """The robot's link: over LCM at `lcm_url`, or on its bus at `port` (a robot
    description with a `bus`); `lockstep`: the robot behind the port is a lock-step
    simulation."""
    robot = config.description()
    if port:
        from hrp2_drake.hardware.bus_link import BusLink

        if not robot.bus.active:
            raise ValueError(
                f"--port {port}: robot '{robot.name}' has no bus in its description "
                "(use --lcm for a robot with an LCM bridge)"
            )
        return BusLink(robot, port, lockstep=lockstep)
    from hrp2_drake.hardware.lcm_link import LcmLink

    transport = open_transport(lcm_url, timeout=min(config.loop.wait_timeout, 2.0))
    return LcmLink(
        robot, transport, config.channels, controller, config.loop.wait_timeout
    )


def run_control(
    config: ControlConfig,
    motor_model: MotorModel,
    out: Path,
    lcm_url: str = "",
    port: str = "",
    lockstep: bool = False,
    sources: TorqueControlSources | None = None,
) -> dict:
    """The whole `hrp2-drake control`: build the fused controller, connect to the
    robot (over LCM at `lcm_url`, or on its bus at `port`), move to home and run the
    control loop, report (control.md with a latency histogram, control.json,
    control.npz). The summary says why the run ended ("fault"). `config` is validated
    where it was loaded (`validate_config`); `sources`: where its torque-control
    settings came from (`load_on_robot`; None: `config` as the caller made it), for
    the report."""
    robot = config.description()
    motor_model = at_robot_gain(motor_model, robot)
    # The references from home, before connecting (balance's inverse kinematics
    # takes a while); the chain is built for them, and the run's (from the measured
    # pose) replace them once the robot is there (the parts read only their start).
    reference, com_reference = control_references(config)
    controller = FusedController(control_chain_parts(config, motor_model, reference))
    say("compiling the controller's kernels (or loading them from numba's cache) ...")
    warm_up = controller.warm_up()
    link = open_link(config, controller, lcm_url, port, lockstep)
    try:
        say(f"waiting for {robot.name} on {link.name} ...")
        start = link.connect(controller)
        reference, com_reference = approached(config, reference, com_reference, start)
        approach = reference.approach_time
        loop = ControlLoop(
            controller,
            link,
            reference,
            settings=config.loop,
            duration=config.duration + approach,
            com_reference=com_reference,
            start_check=(
                (  # the tick torque control would start at, however t rounds
                    controller.parts.controller_config.start_time
                    - 0.5 * config.period(),
                    standing_check(robot, controller),
                )
                if config.motion == "balance"
                else None
            ),
        )
        say(
            f"running {config.duration} s"
            + (f" after a {approach:.1f} s move home" if approach else "")
        )
        summary = loop.run()
    finally:
        link.close()
    summary["approach_s"] = approach
    summary["warm_up_s"] = warm_up
    summary["torque_control_from"] = (sources or TorqueControlSources()).summary()
    start_time = controller.parts.controller_config.start_time
    return _report(config, robot, loop, summary, out, start_time + approach)


def _report(
    config: ControlConfig,
    robot: RobotDescription,
    loop: ControlLoop,
    summary: dict,
    out: Path,
    torque_start: float,
) -> dict:
    """control.npz, control.json, latency.png and control.md; the summary with the
    tracking errors after torque control started (`torque_start`, s)."""
    signals = loop.signals()
    joints = list(loop.controller.parts.joints)
    cols = [robot.joints.index(j) for j in joints]
    after = signals["t"] >= torque_start + 0.1
    error = signals["q_ref"][after][:, cols] - signals["q_measured"][after][:, cols]
    if "com_ref" in signals:  # the QP's CoM (the model's, estimated) − its reference
        com = signals["balance_com"][after] - signals["com_ref"][after][:, :3]
        distance = np.linalg.norm(com, axis=1) * 1e3
        summary["com_error_mm"] = (
            {"rms": float(np.sqrt(np.mean(distance**2))), "max": float(distance.max())}
            if len(distance)
            else {}
        )
    summary |= {
        "robot": robot.name,
        "period": config.period(),
        "duration": config.duration,
        "controlled_joints": joints,
        "max_error_mrad": (np.abs(error).max(axis=0) * 1e3).tolist()
        if len(error)
        else [],
        "rms_error_mrad": (np.sqrt(np.mean(error**2, axis=0)) * 1e3).tolist()
        if len(error)
        else [],
    }
    out.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out / "control.npz", **signals)
    (out / "control.json").write_text(json.dumps(summary, indent=2))
    _latency_histogram(signals["latency_us"], config.period(), out / "latency.png")
    (out / "control.md").write_text(_markdown(robot, config, summary))
    return summary


def _latency_histogram(latency_us: np.ndarray, period: float, path: Path) -> None:
    fig, ax = pyplot().subplots(figsize=(7, 3.5))
    if len(latency_us):
        bins = np.logspace(
            np.log10(max(latency_us.min(), 1.0)), np.log10(latency_us.max() + 1), 60
        )
        ax.hist(latency_us, bins=bins, color="tab:blue")
        ax.set_xscale("log")
        ax.set_yscale("log")
    ax.axvline(
        period * 1e6,
        color="tab:red",
        linestyle="--",
        label=f"period {period * 1e6:.0f} µs",
    )
    ax.set_xlabel("samples in → command out (µs)")
    ax.set_ylabel("ticks")
    legend_beside(ax, fontsize=None)
    ax.set_title("Controller ticks")
    save_figure(fig, path, tight=True)


def _markdown(robot, config: ControlConfig, summary: dict) -> str:
    lines = [
        f"# Torque control of {robot.name} ({summary['link']['name']})",
        "",
        f"{config.duration} s at {1 / config.period():.0f} Hz, {_clock(robot)}; "
        f"motion: {config.motion}.",
        "",
        TorqueControlSources(**summary["torque_control_from"]).markdown(
            config.balance.torque
            if config.motion == "balance"
            else config.torque_control
        ),
        "",
        *_balance_lines(config, summary),
        f"**How the run ended:** {run_ending(summary)}",
        "",
        f"**Torque control active:** {summary['torque_share'] * 100:.1f}% of the ticks "
        "after start-up (start_time + the supervisor's ramp).",
        f"**Gave up for good** (more faults than the supervisor's max_reentries): "
        f"{'yes' if summary['gave_up'] else 'no'}.",
        "",
        *_error_lines(robot, summary),
        *_tick_lines(config, summary),
        *_bus_section(robot, summary),
        *_fallback_lines(summary),
    ]
    return "\n".join(lines) + "\n"


def _error_lines(robot: RobotDescription, summary: dict) -> list[str]:
    """The tracking errors' table (mrad), if torque control started."""
    if not summary["max_error_mrad"]:
        return []
    joints = summary["controlled_joints"]
    labels = robot.labels() if joints == robot.controlled_joints else joints
    return [
        "Errors as the encoders see them (q_ref − q_measured, mrad), after torque "
        "control started:",
        "",
        *markdown_table(
            [None, *labels],
            [
                [name, *(f"{v:.2f}" for v in summary[key])]
                for name, key in (
                    ("maximum", "max_error_mrad"),
                    ("RMS", "rms_error_mrad"),
                )
            ],
        ),
        "",
    ]


def _tick_lines(config: ControlConfig, summary: dict) -> list[str]:
    """The ticks' latency, overruns and refused samples, the warm-up and the
    operating system's real-time settings."""
    lat = summary["latency_us"]
    rt = summary.get("real_time", {})
    return [
        "## Ticks",
        "",
        f"{summary['ticks']} ticks; samples in → command out (the tick and its send): "
        f"p50 {lat['p50']:.0f} µs, p99 {lat['p99']:.0f} µs, p99.9 {lat['p99.9']:.0f} "
        f"µs, max {lat['max']:.0f} µs; {summary['overruns']} periods whose exchange "
        "and tick took longer than the period (the longest run of consecutive ones: "
        f"{summary['longest_overrun_run']}; followed by a fallback within 50 ms: "
        f"{summary['overruns_followed_by_a_fallback']}); {summary['refused_samples']} "
        "samples refused (timestamp not advancing).",
        f"Kernels compiled, or loaded from numba's cache, before the loop: "
        f"{summary['warm_up_s']:.2f} s; none compiled while it ran.",
        f"Operating system: CPU {rt.get('cpu')}, scheduler {rt.get('scheduler')}"
        + (f" ({rt['error'].strip('; ')})" if rt.get("error") else "")
        + "; garbage "
        "collector frozen and disabled in the loop"
        + ("" if config.loop.real_time.freeze_gc else " (not: freeze_gc is off)")
        + ".",
        "",
        "![latency](latency.png)",
        "",
    ]


def _fallback_lines(summary: dict) -> list[str]:
    """The supervisor's events (or None.) and the overruns' times."""
    lines = ["## Fallbacks", ""]
    if summary["events"]:
        lines += markdown_table(
            ["t (s)", "what", "reason"],
            [
                [f"{e['t']:.3f}", f"{e['what']}", f"{e['reason']}"]
                for e in summary["events"]
            ],
            align="rll",
        )
    else:
        lines.append("None.")
    if summary["overrun_times"]:
        lines += [
            "",
            "Overruns at t = "
            + ", ".join(f"{x:.3f}" for x in summary["overrun_times"])
            + " s.",
        ]
    return lines


def _balance_lines(config: ControlConfig, summary: dict) -> list[str]:
    """With `motion: balance`: the CoM motion and the QP's CoM against it."""
    if config.motion != "balance":
        return []
    motion, error = config.com_motion, summary.get("com_error_mm")
    lines = [
        f"Balance on the soles: the CoM ±{motion.amplitude * 1e3:g} mm along "
        f"{motion.axis}, a {motion.period:g} s sinusoid from {config.settle:g} s; the "
        "CoM reference computed by the controller (the robot's bridge sends sensors "
        "only).",
    ]
    if error:
        lines.append(
            "The QP's CoM (the model's, from the base estimated from the soles: not "
            f"ground truth) against its reference: RMS {error['rms']:.2f} mm, "
            f"maximum {error['max']:.2f} mm, after torque control started."
        )
    return lines + [""]


def run_ending(summary: dict) -> str:
    """Why the run ended and what the robot was left with, in one sentence."""
    what = summary["fault"] or "its duration"
    when = f" at t = {summary['fault_time']:.3f} s" if summary["fault"] else ""
    return f"{what}{when}; {summary['ending']}."


def _clock(robot: RobotDescription) -> str:
    if robot.bus.active:
        return (
            f"the loop's own clock on the bus ({robot.bus.model} x "
            f"{len(robot.bus.ids)} at {robot.bus.baud / 1e6:g} Mbit/s: one sync read "
            "and one sync write per period)"
        )
    return "message-driven (the robot's encoder message clocks each tick)"


def _bus_section(robot: RobotDescription, summary: dict) -> list[str]:
    """The bus's budget, the measured cycle, and its faults per servo."""
    if not robot.bus.active:
        return []
    timing = robot.bus.timing()
    link = summary["link"]
    cycle = summary["cycle_us"]
    rows = [
        [
            servo,
            joint,
            f"{c['no_status']}",
            f"{c['corrupt']}",
            f"{c['hardware_alerts']}",
        ]
        for (servo, c), joint in zip(link["servos"].items(), robot.joints)
    ]
    return [
        "## The bus",
        "",
        "Budget per period (wire time, return delays, the adapter's latency timer, the "
        f"compute allowance): {timing.describe()}; the period is "
        f"{summary['period'] * 1e6:.0f} µs. Measured, sync read to sync write sent: "
        f"p50 {cycle['p50']:.0f} µs, p99 {cycle['p99']:.0f} µs, max {cycle['max']:.0f} "
        f"µs; {link['late_periods']} periods started more than a period late (the "
        f"largest lag {link['max_lag_ms']:.1f} ms); {link['incomplete_periods']} "
        "periods without every servo's status.",
        "",
        *markdown_table(
            ["ID", "joint", "no status", "corrupt status", "hardware alerts"],
            rows,
            align="llrrr",
        ),
        "",
    ]


def run_sim_robot(
    config: StationConfig,
    lcm_url: str,
    duration: float,
    out: Path | None,
    channels: LcmChannels | None = None,
    rate: float = 1.0,
    watchdog_periods: int = 5,
    lockstep: bool = False,
) -> dict:
    """The whole `hrp2-drake sim-robot`: `RobotBridge` in real time (or at `rate` times
    it, or in lock step with the controller's commands) for `duration` s (inf: until
    SIGTERM or Ctrl-C); writes its ground truth (sim_robot.npz: t, state_true,
    q_measured, q_cmd, holding, commanded) to `out` on exit. `config` is validated
    where it was loaded (`validate_config`)."""
    bridge_config = BridgeConfig(
        duration=duration,
        rate=rate,
        watchdog_periods=watchdog_periods,
        lockstep=lockstep,
    )
    bridge_config.validate()
    transport = open_transport(lcm_url)
    try:
        bridge = RobotBridge(config, transport, channels, bridge_config)
        say(f"{bridge.robot.name} on {lcm_url}")
        summary = bridge.run()
    finally:
        transport.close()
    if out is not None:
        out.mkdir(parents=True, exist_ok=True)
        np.savez_compressed(
            out / "sim_robot.npz",
            joint_names=np.array(bridge.robot.joints),
            **bridge.signals(),
        )
        (out / "sim_robot.json").write_text(json.dumps(summary, indent=2))
    return summary
