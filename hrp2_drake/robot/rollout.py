"""Rollouts of a servo model on a real log: the logged command in, the simulated
position out, compared with the measured one (the way BAM and PACE judge an actuator
model: position MAE and maximum error on logs it was not fitted on).

A rollout replays one `RobotLog` open loop: the robot's MultibodyPlant starts at the
logged initial position at rest, a servo system turns the logged command (and the
logged servo-on mask, a real servo's torque_enable) into joint torques, and the plant
integrates them for the length of the log. Nothing of the measured trajectory after
the first sample enters the simulation.

.. code-block:: text

      ┌──────────────────┐ q_cmd  ┌────────────┐ actuation ┌───────┐ state
      │ q_cmd (ZOH, log) ├───────►│            ├──────────►│ plant ├───┬──► q_sim
      └──────────────────┘        │   servo    │           └───────┘   │
      ┌──────────────────┐enabled │ (factory)  │◄── state ─────────────┘
      │ valid (ZOH, log) ├───────►│            │
      └──────────────────┘        └────────────┘

The servo is any system a factory `servo(plant, joint_names)` builds with input ports
"q_cmd", "state" and optionally "enabled", and output port "actuation":
`model_servo` (an identified `MotorModel`, `MotorModelServo`) or `emulated_servo`
(the emulated servo, `EmulatedPositionServo`). `hrp2-drake validate` goes through
`rollout`, and so should anything else that replays a log (a servo's calibration on
logs).
"""

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from pydrake.multibody.plant import MultibodyPlant
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import (
    BasicVector,
    Context,
    Diagram,
    DiagramBuilder,
    LeafSystem,
)
from pydrake.systems.primitives import TrajectorySource
from pydrake.trajectories import PiecewisePolynomial

from hrp2_drake.description import RobotDescription
from hrp2_drake.identification.logs import RobotLog
from hrp2_drake.identification.motor_model import MotorModel
from hrp2_drake.multibody import JointIndexing, joint_indexing
from hrp2_drake.robot.servo import EmulatedPositionServo, ServoParams
from hrp2_drake.simulation import LoggedPort, WitnessFreeLeafSystem, add_loggers

#: Builds the servo of a rollout for a finalized plant and the log's joints: a system
#: with input ports "q_cmd", "state" (and optionally "enabled") and output port
#: "actuation".
ServoFactory = Callable[[MultibodyPlant, Sequence[str]], LeafSystem]


class MotorModelServo(WitnessFreeLeafSystem):
    """A position servo that obeys an identified motor model (paper eq. 6 solved for
    the torque), with the servo's documented output saturation.

    .. code-block:: text

                   ┌────────────────┐
        q_cmd ────►│                │
        state ────►│ MotorModelServo├──► actuation
      enabled ────►│                │
                   └────────────────┘

    Per joint, with Δq = clip(q_cmd − q, −Δq_sat, Δq_sat):

        τ = (Δq − k_v q̇ − k_c sign(q̇)) / k_tau    (eq. 6 for τ; enabled)
        τ = 0                                       (servo off)

    Δq_sat is where the servo's output (its PWM duty, its current command)
    saturates (`PositionLoopDescription.saturation_error`): on a voltage-limited
    servo eq. 6 with Δq held there is the torque-speed line τ = (Δq_sat − k_v q̇) /
    k_tau. Servo off, the model knows no friction (eq. 6 has none apart from the
    servo's own loop): the joint is free.

    Ports:
        q_cmd: commanded joint positions (rad), n = len(joint_names), joint order.
        state: the plant's state [q; v].
        enabled: per joint, 1 on, 0 off (> 0.5: on); a real servo's torque_enable.
        actuation: joint torques (N·m) in the plant's actuation order.

    Timing: direct feedthrough, no state. A discrete plant reads its actuation
    input at the start of each step, from the state at that time, and holds it over
    the step; `EmulatedPositionServo` computes its output the same way (from the state
    port, in the output's calc; its discrete state only carries the latency buffer
    and the direction state). So both servos apply τ(q_cmd(t_k), x(t_k)) over
    [t_k, t_k + h], and a model equivalent to the emulator's law gives the same
    trajectory to rounding (tests/test_rollout.py). A periodic discrete update with
    a state output port instead sees, at t_k, the state after that tick's plant
    step (x(t_k+1), the plant's step being processed first) with the command of
    t_k: the same state feedback, but one step of command latency that neither the
    emulator nor eq. 6 has (measured: the whole trajectory shifted by exactly one
    step).
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        model: MotorModel,
        joint_names: Sequence[str],
        delta_q_max: float | Sequence[float] = math.inf,
    ):
        """
        Args:
            plant: the finalized plant whose state the servo reads and drives.
            model: the motor model at the servo's gain, with every joint of
                `joint_names`.
            joint_names: the servo's joints (the order of q_cmd and enabled).
            delta_q_max: Δq_sat (rad), one for all or one per joint; inf: no
                saturation.
        """
        super().__init__()
        self._indexing = joint_indexing(plant, joint_names)
        if np.any(self._indexing.u < 0):
            missing = [n for n, u in zip(joint_names, self._indexing.u) if u < 0]
            raise ValueError(f"MotorModelServo: joints without actuator: {missing}")
        n = len(joint_names)
        self._model = model.subset(list(joint_names))
        delta_q_max = np.broadcast_to(np.asarray(delta_q_max, float), (n,)).copy()
        if not np.all(delta_q_max > 0):
            raise ValueError(
                f"MotorModelServo: delta_q_max must be > 0, got {delta_q_max}"
            )
        self._delta_q_max = delta_q_max
        self._minus_delta_q_max = -delta_q_max
        self._state_q = self._indexing.q
        self._state_v = plant.num_positions() + self._indexing.v
        self._zeros = np.zeros(n)
        self._num_actuators = plant.num_actuators()
        self._q_cmd = self.DeclareVectorInputPort("q_cmd", n)
        self._state = self.DeclareVectorInputPort(
            "state", plant.num_positions() + plant.num_velocities()
        )
        self._enabled = self.DeclareVectorInputPort("enabled", n)
        self.DeclareVectorOutputPort("actuation", plant.num_actuators(), self._calc)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return self._indexing.names

    @property
    def model(self) -> MotorModel:
        """The motor model it obeys (its joints in the servo's order)."""
        return self._model

    @property
    def delta_q_max(self) -> np.ndarray:
        """Δq_sat per joint (rad; inf: none)."""
        return self._delta_q_max.copy()

    def joint_torques(
        self, q_cmd: np.ndarray, q: np.ndarray, v: np.ndarray, enabled: np.ndarray
    ) -> np.ndarray:
        """τ (N·m) per joint for commands q_cmd and positions q (rad), velocities v
        (rad/s) and the servo-on mask (class docstring)."""
        delta_q = np.minimum(
            self._delta_q_max, np.maximum(self._minus_delta_q_max, q_cmd - q)
        )
        tau = self._model.torque(delta_q, v)  # eq. 6 solved for τ
        return np.where(enabled > 0.5, tau, self._zeros)

    def _calc(self, context: Context, output: BasicVector) -> None:
        x = self._state.Eval(context)
        tau = self.joint_torques(
            self._q_cmd.Eval(context),
            x[self._state_q],
            x[self._state_v],
            self._enabled.Eval(context),
        )
        actuation = np.zeros(self._num_actuators)
        actuation[self._indexing.u] = tau
        output.set_value(actuation)


def model_servo(
    robot: RobotDescription,
    model: MotorModel,
    gain: float | None,
    saturate: bool = True,
) -> ServoFactory:
    """The factory of a `MotorModelServo` obeying `model` at servo gain `gain` (the
    servo's own units; `MotorModel.at_gain`), saturated where the robot's position
    loop saturates at that gain (`saturate=False`: never).

    Raises:
        ValueError: the model holds at a gain and `gain` is None (the model at the
            log's gain is unknown).
    """
    if model.gain and gain is None:
        raise ValueError(
            f"the motor model holds at servo gain {model.gain:g}: give the gain of "
            "the log it is rolled out on"
        )
    at_gain = model.at_gain(gain)
    delta_q_max = robot.position_loop.saturation_error(gain) if saturate else math.inf

    def factory(plant: MultibodyPlant, joint_names: Sequence[str]) -> LeafSystem:
        return MotorModelServo(plant, at_gain, joint_names, delta_q_max)

    return factory


def emulated_servo(
    params: ServoParams,
    gain: float | None,
    off: Sequence[str] = (),
    initial_q_cmd: Sequence[float] | None = None,
) -> ServoFactory:
    """The factory of the emulated servo (`EmulatedPositionServo`, with its "enabled"
    port) with `params` at servo gain `gain` (`ServoParams.at_gain`; None: as they
    are), its period the plant's step, mechanisms `off` switched off;
    `initial_q_cmd`: what its latency buffer holds at the start (None: zeros)."""
    at_gain = params.at_gain(gain) if gain else params

    def factory(plant: MultibodyPlant, joint_names: Sequence[str]) -> LeafSystem:
        return EmulatedPositionServo(
            plant,
            at_gain,
            joint_names,
            period=plant.time_step(),
            initial_q_cmd=initial_q_cmd,
            off=off,
            enable_port=True,
        )

    return factory


def twin_servo(params: ServoParams, log: RobotLog) -> ServoFactory:
    """The servo factory of a digital twin (a servo file's `params`) replaying `log`:
    the emulated servo at the log's gain, its latency buffer holding the log's first
    command."""
    return emulated_servo(params, log.gain, initial_q_cmd=log.q_cmd[0])


@dataclass
class RolloutResult:
    """One rollout.

    Attributes:
        log: the log it replayed.
        q_sim: the simulated joint positions (rad), (m, n), on the log's grid
            (row k: the state after the plant steps up to log.t[k]).
        wall_time: the simulation's wall-clock time (s), building excluded.
    """

    log: RobotLog
    q_sim: np.ndarray
    wall_time: float


@dataclass
class RolloutErrors:
    """Position errors q_sim − q_measured per joint (rad), over the whole log and
    over the servo-on samples only (NaN if there are none)."""

    mae: np.ndarray
    max_error: np.ndarray
    mae_servo_on: np.ndarray
    max_error_servo_on: np.ndarray
    servo_on_samples: int


def _held(t: np.ndarray, values: np.ndarray, step: float) -> PiecewisePolynomial:
    """Sample k of `values` (m, rows) held from t_k − step/2 to t_(k+1) − step/2
    (`step`: the plant's step, at most the log's period): the plant's tick at t_k
    reads sample k even when its time and the log's grid differ by rounding (a
    sliced log is re-zeroed by a subtraction). The last sample is repeated at an
    extra break, since a zero-order hold never returns its last sample."""
    shift = 0.5 * step
    breaks = np.append(t - shift, t[-1] + shift)
    samples = np.vstack([values, values[-1:]]).T
    return PiecewisePolynomial.ZeroOrderHold(breaks, samples)


def rollout(
    robot: RobotDescription,
    log: RobotLog,
    servo: ServoFactory,
    time_step: float = 0.001,
) -> RolloutResult:
    """Replays `log` on the robot driven by `servo` (module docstring).

    The plant: the robot's model (fixed robots welded at their base pose), discrete
    at `time_step`, gravity on, no contact; it starts at log.q_measured[0] at rest.
    The command and the servo-on mask are held from each log sample to the next;
    the simulated q is logged on the log's grid.

    Raises:
        ValueError: the log is shorter than two samples, its period is below
            `time_step`, or its joints are not the plant's.
    """
    _check_rollout(log, time_step)
    period = log.period
    diagram, plant, indexing, logger = _rollout_diagram(robot, log, servo, time_step)

    simulator = Simulator(diagram)
    context = simulator.get_mutable_context()
    plant_context = plant.GetMyMutableContextFromRoot(context)
    q0 = plant.GetPositions(plant_context)
    q0[indexing.q] = log.q_measured[0]
    plant.SetPositions(plant_context, q0)
    plant.SetVelocities(plant_context, np.zeros(plant.num_velocities()))

    wall0 = time.perf_counter()
    simulator.Initialize()
    # Past the last grid time by less than a step, so that rounding of the re-zeroed
    # grid cannot drop the last sample.
    simulator.AdvanceTo(float(log.t[-1]) + 0.5 * min(period, time_step))
    wall_time = time.perf_counter() - wall0

    state = logger.data(context).T
    q_sim = _on_log_grid(log, logger.sample_times(context), state[:, indexing.q])
    return RolloutResult(log=log, q_sim=q_sim, wall_time=wall_time)


def _check_rollout(log: RobotLog, time_step: float) -> None:
    """Raises ValueError unless the log has two samples or more and a period of at
    least the finite, positive `time_step` (s)."""
    m = len(log.t)
    if m < 2:
        raise ValueError(f"rollout: log '{log.name}' has {m} samples, needs at least 2")
    if not (math.isfinite(time_step) and time_step > 0):
        raise ValueError(f"rollout: time_step must be finite and > 0, got {time_step}")
    period = log.period
    if period < time_step * (1 - 1e-9):
        raise ValueError(
            f"rollout: log '{log.name}' has period {period:g} s, below the plant's "
            f"time step {time_step:g} s"
        )


def _rollout_diagram(
    robot: RobotDescription, log: RobotLog, servo: ServoFactory, time_step: float
) -> tuple[Diagram, MultibodyPlant, JointIndexing, LoggedPort]:
    """The rollout's diagram (module docstring): (diagram, plant, the log's joints in
    the plant, the logger of the plant's state every log period)."""
    names = list(log.joint_names)
    n = len(names)
    builder = DiagramBuilder()
    plant = builder.AddNamedSystem("plant", MultibodyPlant(time_step))
    robot.add_model(plant)
    plant.Finalize()
    indexing = joint_indexing(plant, names)
    servo_system = builder.AddNamedSystem("servo", servo(plant, names))
    builder.Connect(plant.get_state_output_port(), servo_system.GetInputPort("state"))
    builder.Connect(
        servo_system.GetOutputPort("actuation"), plant.get_actuation_input_port()
    )
    command = builder.AddNamedSystem(
        "q_cmd", TrajectorySource(_held(log.t, log.q_cmd, time_step))
    )
    builder.Connect(command.get_output_port(), servo_system.GetInputPort("q_cmd"))
    if servo_system.HasInputPort("enabled"):
        mask = np.repeat(log.valid.astype(float)[:, None], n, axis=1)
        enabled = builder.AddNamedSystem(
            "enabled", TrajectorySource(_held(log.t, mask, time_step))
        )
        builder.Connect(enabled.get_output_port(), servo_system.GetInputPort("enabled"))
    loggers = add_loggers(builder, {"state": plant.get_state_output_port()}, log.period)
    return builder.Build(), plant, indexing, loggers["state"]


def _on_log_grid(log: RobotLog, sample_times: np.ndarray, q: np.ndarray) -> np.ndarray:
    """The logged joint positions q (one row per logger sample at `sample_times`, s)
    on the log's grid, (m, n); a RuntimeError if a grid time has no sample."""
    m = len(log.t)
    rows = np.rint(sample_times / log.period).astype(int)
    q_sim = np.full((m, q.shape[1]), np.nan)
    keep = rows < m
    q_sim[rows[keep]] = q[keep]
    if np.any(np.isnan(q_sim)):
        raise RuntimeError(
            f"rollout: the logger missed {int(np.isnan(q_sim[:, 0]).sum())} of the "
            f"{m} grid times of log '{log.name}'"
        )
    return q_sim


def rollout_errors(log: RobotLog, q_sim: np.ndarray) -> RolloutErrors:
    """MAE and maximum |q_sim − q_measured| per joint (rad), over the whole log and
    over its servo-on samples."""
    error = np.abs(np.asarray(q_sim, float) - log.q_measured)
    on = error[log.valid]
    if len(on):
        mae_on, max_on = on.mean(axis=0), on.max(axis=0)
    else:
        mae_on = max_on = np.full(error.shape[1], np.nan)
    return RolloutErrors(
        mae=error.mean(axis=0),
        max_error=error.max(axis=0),
        mae_servo_on=mae_on,
        max_error_servo_on=max_on,
        servo_on_samples=int(log.valid.sum()),
    )
