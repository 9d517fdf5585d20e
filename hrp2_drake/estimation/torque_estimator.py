"""FloatingBaseTorqueEstimator: joint torques of a robot, floating-base or welded to the
world, from encoders, one IMU (optional for a fixed base) and 6-axis F/T sensors (paper
Sec. 2), and `add_estimator`, which wires the whole estimation chain (Savitzky-Golay
filters + estimator) to a robot diagram. `TorqueEstimatorStep` is the estimator's
per-tick arithmetic on plain arrays (hrp2_drake.step), which the LeafSystem runs.

The method (paper Sec. 2.2-2.4), on a private model of the robot built from the given
plant (the "internal model", see below):

1. Base motion from the IMU (Sec. 2.3 and its footnote 1, "move the base in the model").
   Joint torques depend on neither the pose of the base nor its linear velocity, and a
   uniform gravity field is equivalent to an upward acceleration of the whole system.
   So the internal model has no gravity, every acceleration is a *proper* acceleration
   (acceleration minus gravity, what an accelerometer reads), and its floating base is
   the IMU frame itself, at the identity pose with zero linear velocity: its angular
   velocity is the gyro reading and its spatial acceleration [α; a] is the measured
   angular acceleration (filtered gyro derivative, or zero) and the accelerometer's
   reading, with no kinematics to compute.
   A robot welded to the world (fixed base) may have no IMU (config.imu_frame empty):
   gravity is known, so the model's root is the base's frame B, at rest, with the
   constant proper acceleration [0; R_BW (−g_W)] (g_W the plant's gravity, R_BW from
   the plant's default pose of the base). With an IMU (e.g. an arm on a moving
   platform) a fixed base is treated as a floating one: the IMU gives the motion.
2. F/T compensation (Sec. 2.2). Each sensor reads S, the wrench that the subtree below
   it exerts on the body above it. Newton-Euler on that subtree (with proper
   accelerations, so gravity is included) gives the external wrench on it,
   F_total = S − offset + Σ_b Ḣ_b, where Ḣ_b is the rate of change of momentum of each
   body b below the sensor, about the sensor origin (see "Offset calibration" for the
   offset). In the internal model each sensor is a 6-dof joint (at the identity, at
   rest, for ever) between the subtree and a massless mount on the joint above it, so
   one inverse dynamics without external wrenches gives Σ_b Ḣ_b of every sensor at
   once: the generalized forces of those joints, [torque about So; force] in S. Exact,
   also with moving links below the sensor (HRP-2's grippers).
   Nested sensors (Sec. 2.2; iCub's leg has one in the thigh and one at the ankle): an
   outer sensor A's joint carries A's whole subtree, nested sensors included, so
   F_A,total is the external wrench on all of it. A's external wrench is that on its
   *segment*, the bodies between A and the sensors B directly below it:
   F_A = F_A,total − Σ_B X*_AB F_B,total (X*_AB moves a wrench about So_B in S_B to
   about So_A in S_A, from the model's kinematics), i.e. the segment's own
   Newton-Euler F_A = S_A − Σ_B X*_AB S_B + Σ_segment Ḣ_b (offsets removed from each
   reading).
3. Joint torques (Sec. 2.3, eq. 2): the inverse dynamics (RNEA) of the internal model
   with each sensor's external wrench f_m applied to the body right below that sensor
   is G = M v̇ + h − Σ_m J_mᵀ f_m (n + 6 generalized forces on the robot's degrees of
   freedom and the root's; the sensor joints' rows are not used). RNEA is linear in
   the applied forces, and M v̇ + h is step 2's inverse dynamics without them: so G is
   that one's minus Σ_m J_mᵀ f_m, with J_m the Jacobian of the sensor frame S at its
   origin (measured in the model's world, expressed in S), one per sensor on the same
   kinematics; no second inverse dynamics.
4. Unknown wrench (Sec. 2.4). The n + 6 equations G = [J_uᵀ Sᵀ] [f_u; τ] are solved for
   the unknown wrench f_u on one link u (the base by default, or a chosen link such as the
   torso) and τ. A = [J_uᵀ Sᵀ] is square; it is checked to have full column rank at
   construction (it always has for a tree: its root rows hold the invertible 6x6
   J_u,rootᵀ), so the least-squares solution is exact:
   f_u = J_u,root⁻ᵀ G_root, τ = G_joints − J_u,jointsᵀ f_u. With u on the IMU's body (the
   torso for HRP-2, the paper's choice) J_u is constant and J_u,joints = 0, so τ = S G;
   the estimate does not depend on which body is the model's base, so for u = the
   robot's base this is eq. 2. For a fixed base the model's root keeps its 6 degrees of
   freedom: f_u on the base is then the wrench the mounting exerts on it.

The internal model is a copy of the plant's bodies (inertias), frames, joints (revolute,
prismatic, welds) and actuators (rotor inertia, gear ratio), re-rooted at a massless body
welded to the IMU frame (or to the fixed base's frame without IMU; a revolute or
prismatic joint turned around keeps its q and its generalized force with the opposite
axis), plus one mount and one 6-dof joint per F/T sensor; the joint that attaches the
robot to the world (floating or weld) is not copied. Per update, the Drake calls: one
SetPositionsAndVelocities, one inverse dynamics, one Jacobian per F/T sensor (plus one
when the unknown-wrench link moves relative to the IMU, and one relative pose per
nested sensor); the arithmetic around them is two numba kernels (`estimator_inputs`,
`estimator_outputs`; hrp2_drake.kernels). That is what makes the Python estimator run
at 1 kHz with room to spare (scripts/bench_estimator.py).

Reflected rotor inertia: the model's actuators may carry a rotor inertia I_r and a gear
ratio ρ (Drake adds ρ² I_r to the joint's diagonal of the mass matrix). With
`include_rotor_inertia` (default) τ̂ includes it, which is the torque the actuator
applies on the joint when the plant's mass matrix includes it (as in our simulated
HRP-2); without, ρ² I_r q̈ is removed from each joint's torque.

Only rigid-body dynamics enter the internal model: its force elements (joint damping,
springs) are not used and its gravity is off (the plant's gravity enters only as a fixed
base's proper acceleration without IMU); τ̂ is the torque the actuators transmit.
"""

import copy
import math
from dataclasses import dataclass, field
from itertools import starmap
from typing import NamedTuple

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import (
    BodyIndex,
    FixedOffsetFrame,
    FrameIndex,
    JacobianWrtVariable,
    ModelInstanceIndex,
    MultibodyForces,
    QuaternionFloatingJoint,
    RigidBody,
    SpatialInertia,
    WeldJoint,
)
from pydrake.systems.framework import (
    Context,
    DiagramBuilder,
    DiscreteValues,
    OutputPort,
    System,
)
from pydrake.systems.primitives import Adder, Demultiplexer, Multiplexer

from hrp2_drake.description import RobotDescription
from hrp2_drake.estimation.savitzky_golay import EVALUATION_POINTS, SavitzkyGolayFilter
from hrp2_drake.kernels import kernel
from hrp2_drake.multibody import (
    check_joint_names,
    check_vector,
    eval_finite,
    get_frame,
    copy_joint,
    joint_indexing,
    tree_joints,
    tree_parents,
)
from hrp2_drake.step import Step, StepSystem

ANGULAR_ACCELERATION_MODES = ("gyro_derivative", "neglected")
_WHERE = "FloatingBaseTorqueEstimator"
_ROOT = "torque_estimator_imu_root"  # the internal model's floating body


@dataclass
class ForceTorqueSensorConfig:
    """One 6-axis F/T sensor.

    Args:
        frame: name of the sensor frame (any frame or body of the plant). Readings and
            external wrenches are [torque; force] (N·m, N), about its origin, expressed
            in it.
        body: name of the body right below the sensor, on the side away from the base
            (for HRP-2 the foot or hand). The sensor carries this body and all the
            bodies beyond it (e.g. a gripper link), whose weight and inertia it
            compensates; the external wrench is assumed to act on this body. Empty: the
            body of `frame`. `frame` must be rigidly attached to it and not on a body
            below it (for an F/T weld, the body is the weld's child, below the sensor).
            Sensors may be nested (one below another, e.g. a thigh and an ankle
            sensor); two sensors cannot share a body.
    """

    frame: str = ""
    body: str = ""


@dataclass
class TorqueEstimatorConfig:
    """Configuration of FloatingBaseTorqueEstimator and of add_estimator's filters.

    Args:
        joints: names of the n one-dof joints, in the order of every joint vector (q,
            v, vdot, tau); together with the floating base (if any) they must cover
            every degree of freedom of the model.
        imu_frame: name of the IMU frame (gyro and accelerometer axes and origin).
            Empty for no IMU, allowed only for a robot welded to the world (a fixed
            base, whose motion is known: at rest, under the plant's gravity); then the
            estimator has no imu_* ports.
        sensors: F/T sensors by name (the name makes the ports wrench_<name> and
            external_wrench_<name>).
        base_body: name of the base body: the floating base body, or for a robot
            welded to the world a body welded to it (directly or through welds). Empty:
            the model's unique floating base or, without any, its unique body welded
            directly to the world.
        angular_acceleration: "gyro_derivative" (the IMU body's angular acceleration
            is the imu_angular_acceleration input, the filtered derivative of the gyro)
            or "neglected" (it is taken as zero and that input is not read; paper
            Sec. 2.3).
        include_rotor_inertia: include the actuators' reflected rotor inertia ρ² I_r
            in τ̂.
        unknown_wrench_body: the link u that carries the unknown wrench (Sec. 2.4);
            empty for the base (then τ̂ is eq. 2; for a fixed base, f_u is the
            mounting's wrench on it). For a fixed base, another link assumes the
            mounting exerts no wrench (a fixed-base approximation of a free robot,
            e.g. hanging from strings tied to u).
        offset_calibration_time: length (s) of the start-up F/T offset calibration, 0
            for none (see the estimator's docstring).
        offset_calibration_start: time (s) the calibration starts, to skip the
            filters' start-up (their windows fill with the sensors' first samples;
            the default leaves 2.5 windows of 80 ms).
        period: the update period (s) of the estimator and of the filters.
        window: number of samples N of the Savitzky-Golay filters of add_estimator
            (the paper: one window for all, so all estimates refer to the same time).
        evaluation: Savitzky-Golay evaluation point, "centre" (delay (N - 1) / 2
            samples, the paper's choice) or "end".
        windows: per-signal windows instead of `window` (the paper's future work:
            "the same delay for all the sensors ... there is room for
            improvement"), by joint name (its encoder), F/T sensor name, or "imu"
            (accelerometer and gyro). Every window is centred on the longest one's
            centre (of `window` and these), so eq. 2 still combines estimates of one
            instant, delayed by (longest − 1) / 2 samples: a shorter window skips the
            newest samples. "centre" only; each of the longest one's parity.
    """

    joints: list[str] = field(default_factory=list)
    imu_frame: str = ""
    sensors: dict[str, ForceTorqueSensorConfig] = field(default_factory=dict)
    base_body: str = ""
    angular_acceleration: str = "gyro_derivative"
    include_rotor_inertia: bool = True
    unknown_wrench_body: str = ""
    offset_calibration_time: float = 0.0
    offset_calibration_start: float = 0.2
    period: float = 0.001
    window: int = 80
    evaluation: str = "centre"
    windows: dict[str, int] = field(default_factory=dict)

    def span(self) -> int:
        """The longest window, whose centre every filter's estimates refer to."""
        return max([self.window, *self.windows.values()])

    def delay_samples(self) -> float:
        """The filters' common evaluation point, in samples before the newest."""
        return (self.span() - 1) / 2 if self.evaluation == "centre" else 0.0

    def window_of(self, signal: str) -> int:
        """The window of a joint's encoder, an F/T sensor or the "imu"."""
        return self.windows.get(signal, self.window)

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it)."""
        where = "TorqueEstimatorConfig"
        check_joint_names(self.joints, where)
        for name, sensor in self.sensors.items():
            if not (name and name.replace("_", "a").isalnum() and name.isascii()):
                raise ValueError(
                    f"{where}.sensors: sensor name '{name}' must be a non-empty "
                    "snake_case identifier (it names ports)"
                )
            if not isinstance(sensor, ForceTorqueSensorConfig):
                raise ValueError(
                    f"{where}.sensors['{name}'] must be a ForceTorqueSensorConfig, "
                    f"got {type(sensor).__name__}"
                )
            if not sensor.frame:
                raise ValueError(f"{where}.sensors['{name}'].frame is empty")
        if self.angular_acceleration not in ANGULAR_ACCELERATION_MODES:
            raise ValueError(
                f"{where}.angular_acceleration='{self.angular_acceleration}' must be "
                f"one of {ANGULAR_ACCELERATION_MODES}"
            )
        for name in ("offset_calibration_time", "offset_calibration_start"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"{where}.{name}={value} must be a finite number >= 0 (s)"
                )
        if not (math.isfinite(self.period) and self.period > 0):
            raise ValueError(f"{where}.period={self.period} must be > 0 (s)")
        if (
            isinstance(self.window, bool)
            or not isinstance(self.window, int)
            or (self.window < 3)
        ):
            raise ValueError(
                f"{where}.window={self.window!r} must be an integer >= 3 (the encoder "
                "filter fits a parabola)"
            )
        if self.evaluation not in EVALUATION_POINTS:
            raise ValueError(
                f"{where}.evaluation='{self.evaluation}' must be one of "
                f"{EVALUATION_POINTS}"
            )
        signals = [*self.joints, *self.sensors, *(["imu"] if self.imu_frame else [])]
        for name, window in self.windows.items():
            if name not in signals:
                raise ValueError(
                    f"{where}.windows: '{name}' is not a joint, an F/T sensor or "
                    f"'imu' of this estimator ({len(signals)} signals: e.g. "
                    f"{signals[:3]})"
                )
            if isinstance(window, bool) or not isinstance(window, int) or window < 3:
                raise ValueError(
                    f"{where}.windows['{name}']={window!r} must be an integer >= 3"
                )
        if self.windows and len({self.window, *self.windows.values()}) > 1:
            if self.evaluation != "centre":
                raise ValueError(
                    f"{where}.windows: per-signal windows need evaluation='centre', "
                    f"got '{self.evaluation}'"
                )
            span = self.span()
            for name, window in [("window", self.window), *self.windows.items()]:
                if (span - window) % 2:
                    field_name = name if name == "window" else f"windows['{name}']"
                    raise ValueError(
                        f"{where}.{field_name}={window}: of another parity than the "
                        f"longest window, {span}, so its centre (the instant it "
                        "estimates) cannot be the longest one's"
                    )


def estimator_config(
    robot: RobotDescription, window: int = 80, **options
) -> TorqueEstimatorConfig:
    """The estimator of paper Sec. 2 for `robot`: its joints, IMU (if any), F/T
    sensors and unknown-wrench link, `window` samples per Savitzky-Golay filter;
    `options` set the other fields of TorqueEstimatorConfig."""
    options.setdefault("unknown_wrench_body", robot.unknown_wrench_body)
    sensors = {
        name: ForceTorqueSensorConfig(frame=sensor.frame, body=sensor.body)
        for name, sensor in robot.force_torque_sensors.items()
    }
    return TorqueEstimatorConfig(
        joints=list(robot.joints),
        imu_frame=robot.imu_frame,
        sensors=sensors,
        window=window,
        **options,
    )


class TorqueEstimate(NamedTuple):
    """What the estimator computes for one sample (see `estimate`).

    Attributes:
        tau: joint torques (N·m, n, config.joints order).
        unknown_wrench: [torque; force] on the unknown-wrench link, about its origin,
            expressed in its frame (N·m, N).
        external_wrenches: (k, 6) compensated external wrench of each sensor, in
            config.sensors order: [torque; force] exerted by the environment on the
            bodies below the sensor (for a sensor with sensors nested below it, on its
            segment: the bodies between it and them), about the sensor origin, in the
            sensor frame.
    """

    tau: np.ndarray
    unknown_wrench: np.ndarray
    external_wrenches: np.ndarray


@dataclass
class _Sensor:
    name: str
    frame: object  # the sensor Frame S (of the user's plant)
    body: RigidBody  # the body right below the sensor, B (of the user's plant)
    X_BS: RigidTransform
    bodies: list[int]  # BodyIndex of every body below the sensor (B's subtree)
    port: object = None
    # In the internal model (see _internal_model):
    model_body: RigidBody | None = None  # B
    model_frame: object = None  # S, on B
    p_BoSo_S: np.ndarray | None = None  # where external wrenches are applied
    joint: object = None  # the 6-dof joint above B
    rows: np.ndarray | None = None  # its 6 velocities


# TorqueEstimatorStep's index table (`_pack`, int64): a header, then the index lists.
(
    _N,  # n, the joints
    _K,  # k, the F/T sensors
    _NQ,  # the internal model's positions,
    _NV,  # and velocities
    _FLAGS,  # _HAS_IMU | _READS_ALPHA | _SUBTRACTS_ROTOR | _MAPS_UNKNOWN
    _ROOT_V,  # the root's velocities [ω; v] in v (the IMU frame's)
    _PAIRS,  # the number of nested (outer, inner) sensor pairs
    # Where each part of the work array starts (x = [q; v] of the model at 0):
    _W_VDOT,  # v̇ of the model (nv)
    _W_RAW,  # the F/T readings (k, 6)
    _W_TOTAL,  # F_total (k, 6)
    _W_APPLIED,  # Σ_m J_mᵀ f_m on the joints' and the root's rows (n + 6)
    _W_ROOT,  # G_root (6)
    _W_POSES,  # X_AB of each pair, (3, 4) [R p] each
    _W_MAP,  # J_u,rootᵀ⁻¹ (6, 6), when u is welded to the root
    _W_ROTOR,  # ρ² I_r (n)
    # Where each index list starts in the table:
    _T_JQ,  # the joints' positions in q (n)
    _T_JV,  # their velocities in v (n), then the root's (6)
    _T_SENSOR_ROWS,  # each sensor joint's velocities (6 k)
    _T_PAIRS,  # (outer, inner) of each pair
    _HEADER,
) = range(20)
_HAS_IMU, _READS_ALPHA, _SUBTRACTS_ROTOR, _MAPS_UNKNOWN = 1, 2, 4, 8


@kernel
def estimator_inputs(q, v, vdot, acc, gyro, alpha, wrenches, work, table):
    """`TorqueEstimatorStep.step`'s inputs into the work array (`_pack`'s layout): q, v
    of the joints and the gyro into x = [q; v] of the internal model, vdot and the
    IMU's α (if read) and proper acceleration into its v̇, the F/T readings (k, 6);
    acc, gyro, alpha are zero-length when not read. Returns the sum of x, v̇ and the
    readings, finite exactly when every entry is (barring an overflow): the step's
    one check of its inputs. Copies only (bitwise)."""
    n = table[_N]
    k = table[_K]
    nq = table[_NQ]
    flags = table[_FLAGS]
    if q.shape[0] != n or v.shape[0] != n or vdot.shape[0] != n:
        raise ValueError("TorqueEstimatorStep.step: q, v and vdot need n entries each")
    if wrenches.shape[0] != k or wrenches.shape[1] != 6:
        raise ValueError("TorqueEstimatorStep.step: wrenches must be (k, 6)")
    jq = table[_T_JQ]
    jv = table[_T_JV]
    vd = table[_W_VDOT]
    for i in range(n):
        work[table[jq + i]] = q[i]
    for i in range(n):
        work[nq + table[jv + i]] = v[i]
    for i in range(n):
        work[vd + table[jv + i]] = vdot[i]
    if flags & _HAS_IMU:
        if acc.shape[0] != 3 or gyro.shape[0] != 3:
            raise ValueError("TorqueEstimatorStep.step: the IMU inputs need 3 entries")
        root = table[_ROOT_V]
        for i in range(3):
            work[nq + root + i] = gyro[i]
        if flags & _READS_ALPHA:
            if alpha.shape[0] != 3:
                raise ValueError(
                    "TorqueEstimatorStep.step: the IMU inputs need 3 entries"
                )
            for i in range(3):
                work[vd + root + i] = alpha[i]
        for i in range(3):
            work[vd + root + 3 + i] = acc[i]
    raw = table[_W_RAW]
    for s in range(k):
        for i in range(6):
            work[raw + 6 * s + i] = wrenches[s, i]
    total = 0.0
    for i in range(table[_W_TOTAL]):
        total += work[i]
    return total


@kernel
def estimator_outputs(calibrating, G, jacobians, work, state, table):
    """`TorqueEstimatorStep.step`'s arithmetic after Drake's calls (module docstring,
    steps 2 to 4), into `state` (tau, unknown_wrench, the external wrenches, the
    calibration, in that order): from G = M v̇ + h of the internal model (the inverse
    dynamics without applied forces), `jacobians` (one (6, nv) J_m per sensor, in S at
    So, then J_u if u moves; a single unused one when neither), the work array (the
    readings, v̇, the nested pairs' poses, the constants) and `table` (`_pack`). With
    `calibrating`, one more sample of the offsets' running mean first.

    Elementwise as the numpy code before (bitwise): F_total, the calibration, the
    offsets, the copies of G's rows, the rotor term. Reductions, summing products in
    order without fma: Σ_m J_mᵀ f_m (each sensor's 6 products, then the sensors in
    order; Drake's second inverse dynamics before), the 3x3 and 6x6 products of the
    nested poses and the unknown wrench (numpy's matmul before)."""
    n = table[_N]
    k = table[_K]
    flags = table[_FLAGS]
    raw = table[_W_RAW]
    tot = table[_W_TOTAL]
    rows = table[_T_SENSOR_ROWS]
    unknown = n
    external = n + 6
    offsets = n + 6 + 6 * k
    # Step 2: F_total = S + Σ_b Ḣ_b of every sensor.
    for j in range(6 * k):
        work[tot + j] = work[raw + j] + G[table[rows + j]]
    if calibrating:
        # The running mean: offsets += (total − offsets) / count.
        count = state[offsets + 6 * k] + 1.0
        for j in range(6 * k):
            mean_step = work[tot + j] - state[offsets + j]
            mean_step /= count
            state[offsets + j] += mean_step
        state[offsets + 6 * k] = count
    pairs = table[_PAIRS]
    if pairs == 0:  # each sensor's external wrench is its total
        for j in range(6 * k):
            state[external + j] = work[tot + j] - state[offsets + j]
    else:
        for j in range(6 * k):
            work[tot + j] -= state[offsets + j]
        for j in range(6 * k):
            state[external + j] = work[tot + j]
        # F_A −= X*_AB F_B: with X_AB = (R, p), f_A = R f_B, τ_A = R τ_B + p × f_A.
        for m in range(pairs):
            a = table[table[_T_PAIRS] + 2 * m]
            b = table[table[_T_PAIRS] + 2 * m + 1]
            X = work[table[_W_POSES] + 12 * m : table[_W_POSES] + 12 * (m + 1)]
            F_b = work[tot + 6 * b : tot + 6 * b + 6]
            f0 = X[0] * F_b[3] + X[1] * F_b[4] + X[2] * F_b[5]
            f1 = X[4] * F_b[3] + X[5] * F_b[4] + X[6] * F_b[5]
            f2 = X[8] * F_b[3] + X[9] * F_b[4] + X[10] * F_b[5]
            t0 = X[0] * F_b[0] + X[1] * F_b[1] + X[2] * F_b[2]
            t1 = X[4] * F_b[0] + X[5] * F_b[1] + X[6] * F_b[2]
            t2 = X[8] * F_b[0] + X[9] * F_b[1] + X[10] * F_b[2]
            p0, p1, p2 = X[3], X[7], X[11]
            A = external + 6 * a
            state[A] -= t0 + (p1 * f2 - p2 * f1)
            state[A + 1] -= t1 + (p2 * f0 - p0 * f2)
            state[A + 2] -= t2 + (p0 * f1 - p1 * f0)
            state[A + 3] -= f0
            state[A + 4] -= f1
            state[A + 5] -= f2
    # Step 3: G − Σ_m J_mᵀ f_m, the joints' rows into tau, the root's into G_root
    # (each sensor's J_mᵀ f_m a sum over its 6 rows, added to the others' in order).
    jv = table[_T_JV]
    root = table[_ROOT_V]
    groot = table[_W_ROOT]
    applied = table[_W_APPLIED]
    for i in range(n + 6):
        work[applied + i] = 0.0
    for s in range(k):
        J = jacobians[s]
        f = external + 6 * s
        f0, f1, f2 = state[f], state[f + 1], state[f + 2]
        f3, f4, f5 = state[f + 3], state[f + 4], state[f + 5]
        for i in range(n + 6):
            c = table[jv + i]
            work[applied + i] += (
                J[0, c] * f0
                + J[1, c] * f1
                + J[2, c] * f2
                + J[3, c] * f3
                + J[4, c] * f4
                + J[5, c] * f5
            )
    for i in range(n):
        state[i] = G[table[jv + i]] - work[applied + i]
    for r in range(6):
        work[groot + r] = G[root + r] - work[applied + n + r]
    # Step 4: the unknown wrench.
    if flags & _MAPS_UNKNOWN:
        # u welded to the root: f_u = J_u,rootᵀ⁻¹ G_root, J_u,joints = 0.
        T = table[_W_MAP]
        for r in range(6):
            f = 0.0
            for c in range(6):
                f += work[T + 6 * r + c] * work[groot + c]
            state[unknown + r] = f
    else:
        # [J_uᵀ Sᵀ] [f_u; τ] = G (Sec. 2.4): root rows first. Expressed in u, with the
        # root at the identity pose, J_u,root = [R 0; −R[p]× R] (R = R_uW, p = p_WUo),
        # whose inverse transpose is [R −R[p]×; 0 R]: no 6x6 solve.
        J = jacobians[k]
        for r in range(3):
            torque = 0.0
            for c in range(3):
                torque += J[r, root + c] * work[groot + c]
            moment = 0.0
            for c in range(3):
                moment += J[3 + r, root + c] * work[groot + 3 + c]
            force = 0.0
            for c in range(3):
                force += J[r, root + c] * work[groot + 3 + c]
            state[unknown + r] = torque + moment
            state[unknown + 3 + r] = force
        for i in range(n):
            c = table[jv + i]
            projected = 0.0
            for r in range(6):
                projected += J[r, c] * state[unknown + r]
            state[i] -= projected
    if flags & _SUBTRACTS_ROTOR:
        vd = table[_W_VDOT]
        rotor = table[_W_ROTOR]
        for i in range(n):
            state[i] -= work[vd + table[jv + i]] * work[rotor + i]


class TorqueEstimatorStep(Step):
    """The per-tick arithmetic of `FloatingBaseTorqueEstimator` (its docstring:
    inputs, outputs, units, offset calibration, errors; the method in the module
    docstring), on plain arrays, with everything it precomputes: the internal model,
    one context of it (a computation workspace), a zero MultibodyForces, the sensors,
    the kernels' work array and index table (`_pack`).

    `step(t, q, v, vdot, imu_linear_acceleration, imu_angular_velocity,
    imu_angular_acceleration, wrenches)` updates the state in place. Named state
    arrays (`Step`), the outputs named like the estimator's ports:
        tau (n): estimated joint torques τ̂ (N·m), config.joints order.
        unknown_wrench (6): [torque; force] (N·m, N) on the unknown-wrench link.
        external_wrench_<sensor> (6 each, config.sensors order): the compensated
            external wrench [torque; force] (N·m, N), about So, in S.
        calibration (6 k + 1): the F/T offsets in use (k, 6) (N·m, N), then the
            number of calibration samples averaged.

    Per step: a kernel (`estimator_inputs`) writes the inputs into the work array and
    sums them (the check for NaN and infinity); then Drake: one
    SetPositionsAndVelocities, one inverse dynamics, one Jacobian per sensor, one
    relative pose per nested sensor and, unless the unknown-wrench link is rigidly
    attached to the model's root, one more Jacobian; then a kernel
    (`estimator_outputs`) writes the whole state from their results (module docstring,
    steps 2 to 4). For HRP-2 (4 F/T sensors, u on the torso): 6 pybind calls per step
    (the numpy version had 12: a second inverse dynamics, k SpatialForce and k
    AddInForce, a SetZero). Drake returns the inverse dynamics and each Jacobian as a
    new array: those are the per-step allocations (with the tuple that carries the
    Jacobians into the kernel).

    Rounding: step 3's Σ_m J_mᵀ f_m is a sum of products in the kernel where it was
    Drake's second inverse dynamics (the same generalized forces in another order),
    and the 3x3 and 6x6 products were numpy's matmul. Measured against the numpy
    version on HRP-2's closed loop (2 s, tuned right leg, hanging, 4 F/T sensors, u
    on the torso), each tick's inputs given to both: τ̂ within 1.1e-14 N·m (1e-15 of
    the tick's largest |τ̂|), the unknown wrench within 2.3e-13 (of 568 N); the
    external wrenches and the calibration bitwise (elementwise). The other layouts
    (tests/test_estimator_layouts.py: the arm, the nested legs): within 3e-16 of the
    largest entry.
    """

    def __init__(self, plant: MultibodyPlant, config: TorqueEstimatorConfig):
        """
        Args: those of `FloatingBaseTorqueEstimator` (same checks and messages).

        Raises:
            ValueError, KeyError: see FloatingBaseTorqueEstimator.
        """
        super().__init__()
        config.validate()
        if not plant.is_finalized():
            raise ValueError(f"{_WHERE}: the plant must be finalized")
        self._plant = plant
        self._config = copy.deepcopy(config)
        plant_context = plant.CreateDefaultContext()
        self._zero3 = np.zeros(3)
        imu, unknown_frame, nesting = self._check_robot(plant, plant_context, config)
        # The internal model, in which everything is computed (module docstring). Its
        # root is the IMU frame, or the fixed base's frame without IMU.
        root_frame = imu if self._has_imu else self._base.body_frame()
        model, frames = _internal_model(plant, plant_context, root_frame, self._sensors)
        self._model = model
        self._context = model.CreateDefaultContext()
        self._make_work_arrays(plant, plant_context, config, len(nesting))
        # (outer, inner, S_outer, S_inner) for every sensor directly below another.
        self._nesting = [
            (a, b, self._sensors[a].model_frame, self._sensors[b].model_frame)
            for a, b in nesting
        ]
        self._no_forces = MultibodyForces(model)  # stays zero
        self._world = model.world_frame()
        u = frames[int((unknown_frame or self._base.body_frame()).index())]
        self._check_rank(model, u)
        self._unknown_frame, self._unknown_map = self._unknown_wrench_map(model, u)
        self._set_options(config)
        self._make_jacobian_calls()

        k = len(self._sensors)
        self._declare("tau", np.zeros(self._n))
        self._declare("unknown_wrench", np.zeros(6))
        for sensor in self._sensors:
            self._declare(f"external_wrench_{sensor.name}", np.zeros(6))
        # F/T offsets (6 per sensor) then the number of calibration samples.
        self._declare("calibration", np.zeros(6 * k + 1))
        self._finalize()
        self._table = self._pack()

    def _check_robot(
        self, plant: MultibodyPlant, plant_context: Context, config
    ) -> tuple[object, object, list[tuple[int, int]]]:
        """Finds and checks the base, the joints, the IMU, the sensors (their nesting)
        and the unknown-wrench link; returns (IMU frame or None, unknown-wrench frame
        or None for the base, the nested (outer, inner) sensor pairs)."""
        self._base, self._fixed_base = self._find_base(plant, config)
        self._indexing = joint_indexing(plant, config.joints)
        self._n = self._indexing.size
        self._parent = tree_parents(plant, self._base.index())
        self._check_dofs(plant)
        if not self._fixed_base:
            plant.SetFreeBodyPose(plant_context, self._base, RigidTransform())
        self._check_base_jacobian(plant, plant_context)

        imu = self._find_imu(plant, config)
        self._has_imu = imu is not None
        self._sensors = [
            self._make_sensor(plant, plant_context, name, sensor)
            for name, sensor in config.sensors.items()
        ]
        nesting = self._nest_sensors()
        self._reflected_inertia = self._reflected_inertias(plant, plant_context)
        unknown_frame = self._find_unknown_wrench_frame(plant, config)
        below = [b for s in self._sensors for b in s.bodies]
        if self._has_imu and int(imu.body().index()) in below:
            raise ValueError(
                f"{_WHERE}: IMU frame '{config.imu_frame}' is below an F/T sensor"
            )
        return imu, unknown_frame, nesting

    def _make_work_arrays(
        self, plant: MultibodyPlant, plant_context: Context, config, num_pairs: int
    ) -> None:
        """The kernels' work array and where the inputs go in it (index arrays: the
        model's order is not the joints'): x = [q; v] of the model, v̇, the F/T
        readings (k, 6), F_total (k, 6), G_root (6), the pose (3, 4) of each of the
        `num_pairs` nested sensor pairs, then constants (`_pack`); views on it."""
        model = self._model
        root = model.GetBodyByName(_ROOT, model.GetModelInstanceByName(_ROOT))
        start = root.floating_velocities_start_in_v()
        nq, nv = model.num_positions(), model.num_velocities()
        indexing = joint_indexing(model, config.joints)
        k = len(self._sensors)
        # x, v̇, readings, F_total, Σ J_mᵀ f_m, G_root, poses, J_u,rootᵀ⁻¹, ρ² I_r.
        sizes = [nq + nv, nv, 6 * k, 6 * k, self._n + 6, 6, 12 * num_pairs, 36, self._n]
        self._work = np.zeros(sum(sizes))
        self._work_starts = np.cumsum([0, *sizes[:-1]])
        x, vdot, raw, _, _, _, poses, _, _ = np.split(
            self._work, self._work_starts[1:]
        )
        self._x, self._vdot = x, vdot
        self._raw = raw.reshape(k, 6)
        self._poses = poses.reshape(num_pairs, 3, 4)
        model.SetFreeBodyPose(self._context, root, RigidTransform())
        self._x[:nq] = model.GetPositions(self._context)  # the identities, for ever
        self._jq = indexing.q
        self._jv = indexing.v
        self._root_v = slice(start, start + 6)  # [ω; v] of the root (the IMU frame)
        self._root_a = slice(start + 3, start + 6)  # a of the root: accelerometer
        if not self._has_imu:
            # Fixed base, gravity known (step 1): the root (the base frame B) is at
            # rest, ω = α = 0 (left at zero), with proper acceleration R_BW (−g_W).
            R_WB = self._base.EvalPoseInWorld(plant_context).rotation()
            g_W = plant.gravity_field().gravity_vector()
            self._vdot[self._root_a] = R_WB.inverse() @ (-g_W)
        self._sensor_rows = (
            np.concatenate([s.rows for s in self._sensors])
            if self._sensors
            else np.zeros(0, dtype=int)
        )
        self._empty = np.zeros(0)  # an input that is not read

    def _make_jacobian_calls(self) -> None:
        """The arguments of the Jacobians of a step (`_evaluate`): J_m of each sensor
        frame S at So (measured in the model's world, expressed in S), then J_u if u
        moves relative to the root; and the stand-in when there is none (a kernel's
        tuple holds one array at least)."""
        model, context, world = self._model, self._context, self._world
        kV, zero = JacobianWrtVariable.kV, self._zero3
        frames = [sensor.model_frame for sensor in self._sensors]
        if self._unknown_frame is not None:
            frames.append(self._unknown_frame)
        self._jacobian = model.CalcJacobianSpatialVelocity
        self._jacobian_args = [(context, kV, S, zero, world, S) for S in frames]
        self._no_jacobians = (np.zeros((6, model.num_velocities()), order="F"),)

    def _pack(self) -> np.ndarray:
        """The kernels' index table (int64): the header (`_N`..`_T_PAIRS`: sizes, the
        flags, where each part of the work array and of the table starts), then the
        joints' positions and velocities in the model, the sensor joints' velocities
        and the nested pairs; and the constants into the work array (J_u,rootᵀ⁻¹ when u
        is welded to the root, ρ² I_r). The state's layout is the kernel's: tau,
        unknown_wrench, the external wrenches (config.sensors order), calibration."""
        n, k = self._n, len(self._sensors)
        names = [name for name, _ in self.layout()]
        assert names == self.output_names() + ["calibration"]
        assert self.rows("calibration").start == n + 6 + 6 * k
        flags = (
            (_HAS_IMU if self._has_imu else 0)
            | (_READS_ALPHA if self._read_alpha else 0)
            | (_SUBTRACTS_ROTOR if self._subtract_rotor else 0)
            | (_MAPS_UNKNOWN if self._unknown_map is not None else 0)
        )
        root_v = np.arange(self._root_v.start, self._root_v.stop)
        lists = [
            self._jq,
            np.concatenate([self._jv, root_v]),
            self._sensor_rows,
            np.array([index for a, b, _, _ in self._nesting for index in (a, b)]),
        ]
        list_starts = _HEADER + np.cumsum([0, *(len(x) for x in lists[:-1])])
        header = [
            n,
            k,
            self._model.num_positions(),
            self._model.num_velocities(),
            flags,
            self._root_v.start,
            len(self._nesting),
            *self._work_starts[1:],
            *list_starts,
        ]
        assert len(header) == _HEADER
        table = np.concatenate([header, *lists]).astype(np.int64)
        constants = np.split(self._work, self._work_starts[1:])
        if self._unknown_map is not None:
            constants[-2][:] = self._unknown_map.reshape(-1)  # row-major (6, 6)
        constants[-1][:] = self._reflected_inertia
        return table

    def warm_up(self) -> None:
        """Compiles (or loads) `estimator_inputs` and `estimator_outputs` for the
        step's arrays: inputs as the fused controller and the LeafSystem pass them
        (C-contiguous float64; wrenches (k, 6)), Drake's own inverse dynamics and
        Jacobians (F-ordered); on copies of the work array and the state."""
        n, k, empty = self._n, len(self._sensors), self._empty
        work, state = self._work.copy(), self.state.copy()
        imu = np.zeros(3) if self._has_imu else empty
        alpha = np.zeros(3) if self._read_alpha else empty
        zeros = np.zeros(n)
        estimator_inputs(
            zeros, zeros, zeros, imu, imu, alpha, np.zeros((k, 6)), work, self._table
        )
        G = np.zeros(self._model.num_velocities())
        estimator_outputs(False, G, self._jacobians(), work, state, self._table)

    def _set_options(self, config: TorqueEstimatorConfig) -> None:
        self._neglect_alpha = config.angular_acceleration == "neglected"
        self._read_alpha = self._has_imu and not self._neglect_alpha
        self._calibrates = config.offset_calibration_time > 0
        # Calibrate at the updates with start <= t < start + time (half-period margins).
        self._calibration_begin = config.offset_calibration_start - 0.5 * config.period
        self._calibration_end = (
            config.offset_calibration_start
            + config.offset_calibration_time
            - 0.5 * config.period
        )
        self._subtract_rotor = not config.include_rotor_inertia

    def _views_changed(self) -> None:
        k = len(self._sensors)
        self._offsets = self.calibration[:-1].reshape(k, 6)


    # ----------------------------------------------------------------- construction

    @staticmethod
    def _find_base(
        plant: MultibodyPlant, config: TorqueEstimatorConfig
    ) -> tuple[RigidBody, bool]:
        """(base body, fixed): the floating base, or a body welded to the world."""
        world = plant.world_body()
        welded = {int(b.index()) for b in plant.GetBodiesWeldedTo(world)}
        welded.discard(int(world.index()))
        if config.base_body:
            if not plant.HasBodyNamed(config.base_body):
                raise KeyError(
                    f"{_WHERE}: base body '{config.base_body}' is not a body"
                )
            base = plant.GetBodyByName(config.base_body)
            if base.is_floating_base_body():
                return base, False
            if int(base.index()) in welded:
                return base, True
            raise ValueError(
                f"{_WHERE}: base body '{config.base_body}' is not a floating base, nor "
                "welded to the world"
            )
        floating = sorted(int(b) for b in plant.GetFloatingBaseBodies())
        if len(floating) == 1:
            return plant.get_body(BodyIndex(floating[0])), False
        # Bodies welded directly to the world (not through other welded bodies).
        direct = set()
        for j in plant.GetJointIndices():
            joint = plant.get_joint(j)
            ends = {int(joint.parent_body().index()), int(joint.child_body().index())}
            if joint.num_velocities() == 0 and int(world.index()) in ends:
                direct |= ends - {int(world.index())}
        if not floating and len(direct) == 1:
            return plant.get_body(BodyIndex(direct.pop())), True

        def names(indices) -> list[str]:
            return [plant.get_body(BodyIndex(b)).name() for b in sorted(indices)]

        raise ValueError(
            f"{_WHERE}: the plant must have exactly one floating base body, or none "
            "and exactly one body welded to the world; it has floating bases "
            f"{names(floating)} and bodies welded to the world {names(direct)}: give a "
            "model of the robot alone, or name its base in "
            "TorqueEstimatorConfig.base_body"
        )

    def _base_dofs(self) -> int:
        return 0 if self._fixed_base else 6

    def _check_dofs(self, plant: MultibodyPlant) -> None:
        """The base's and config.joints' velocities are all of the plant's, and every
        joint with degrees of freedom but the floating base's is in the robot's tree."""
        for j in plant.GetJointIndices():
            joint = plant.get_joint(j)
            if joint.num_velocities() == 0:
                continue
            child = int(joint.child_body().index())
            if not self._fixed_base and child == int(self._base.index()):
                if joint.parent_body().index() == plant.world_body().index():
                    continue  # the floating base's joint
            parent = int(joint.parent_body().index())
            if parent not in self._parent or child not in self._parent:
                raise ValueError(
                    f"{_WHERE}: joint '{joint.name()}' (between '"
                    f"{joint.parent_body().name()}' and '{joint.child_body().name()}') "
                    f"is not in the tree of the base '{self._base.name()}': only the "
                    "base may be attached to the world; give a model of the robot alone"
                )
        expected = self._base_dofs() + self._n
        if plant.num_velocities() != expected:
            covered = set(self._indexing.v.tolist())
            if not self._fixed_base:
                start = self._base.floating_velocities_start_in_v()
                covered |= set(range(start, start + 6))
            missing = [
                plant.get_joint(j).name()
                for j in plant.GetJointIndices()
                if plant.get_joint(j).num_velocities() > 0
                and plant.get_joint(j).velocity_start() not in covered
            ]
            what = "the fixed base and" if self._fixed_base else "the floating base and"
            raise ValueError(
                f"{_WHERE}: the plant has {plant.num_velocities()} velocities, but "
                f"{what} the {self._n} joints of the config cover {expected}; joints "
                f"not in the config: {missing}"
            )

    def _check_base_jacobian(self, plant: MultibodyPlant, context: Context) -> None:
        """A floating base's velocities must be [ω_WB; v_WBo]; a fixed base has none
        (welded to the world, its motion is the IMU's or none)."""
        if self._fixed_base:
            return
        J = plant.CalcJacobianSpatialVelocity(
            context,
            JacobianWrtVariable.kV,
            self._base.body_frame(),
            self._zero3,
            plant.world_frame(),
            plant.world_frame(),
        )
        start = self._base.floating_velocities_start_in_v()
        if not np.allclose(J[:, start : start + 6], np.eye(6), atol=1e-12):
            raise ValueError(
                f"{_WHERE}: the floating joint of '{self._base.name()}' does not have "
                "velocities [ω_WB; v_WBo] (e.g. a quaternion or rpy floating joint)"
            )

    def _find_imu(self, plant: MultibodyPlant, config: TorqueEstimatorConfig):
        """The IMU frame, or None without IMU (only for a fixed base)."""
        if not config.imu_frame:
            if not self._fixed_base:
                raise ValueError(
                    f"{_WHERE}: TorqueEstimatorConfig.imu_frame is empty, but the base "
                    f"'{self._base.name()}' is floating: its motion comes from the IMU "
                    "(only a robot welded to the world may go without IMU)"
                )
            return None
        imu = get_frame(plant, config.imu_frame, "IMU frame")
        if imu.body().index() == plant.world_body().index():
            raise ValueError(
                f"{_WHERE}: IMU frame '{config.imu_frame}' is on the world"
            )
        if int(imu.body().index()) not in self._parent:
            raise ValueError(
                f"{_WHERE}: IMU frame '{config.imu_frame}' is on body "
                f"'{imu.body().name()}', which is not in the robot's tree"
            )
        return imu

    def _subtree(self, body: int) -> list[int]:
        children: dict[int, list[int]] = {}
        for child, parent in self._parent.items():
            children.setdefault(parent, []).append(child)
        out, stack = [], [body]
        while stack:
            b = stack.pop()
            out.append(b)
            stack.extend(children.get(b, []))
        return sorted(out)

    def _make_sensor(
        self,
        plant: MultibodyPlant,
        context: Context,
        name: str,
        cfg: ForceTorqueSensorConfig,
    ):
        frame = get_frame(plant, cfg.frame, f"F/T sensor '{name}' frame")
        if cfg.body:
            if not plant.HasBodyNamed(cfg.body):
                raise KeyError(
                    f"{_WHERE}: F/T sensor '{name}' body '{cfg.body}' is not a body of "
                    "the plant"
                )
            body = plant.GetBodyByName(cfg.body)
        else:
            body = frame.body()
        index = int(body.index())
        if index not in self._parent:
            raise ValueError(
                f"{_WHERE}: F/T sensor '{name}': body '{body.name()}' is not part of the "
                "robot's tree"
            )
        if index == int(self._base.index()):
            raise ValueError(
                f"{_WHERE}: F/T sensor '{name}': body '{body.name()}' is the base; give "
                "the body right below the sensor"
            )
        welded = {int(b.index()) for b in plant.GetBodiesWeldedTo(body)} | {index}
        on = int(frame.body().index())
        if on not in welded:
            raise ValueError(
                f"{_WHERE}: F/T sensor '{name}': frame '{cfg.frame}' is not rigidly "
                f"attached to body '{body.name()}'"
            )
        bodies = self._subtree(index)
        if on != index and on in bodies:
            # E.g. the ankle link above an F/T weld whose frame is on the foot: the
            # sensor would wrongly carry the ankle link.
            raise ValueError(
                f"{_WHERE}: F/T sensor '{name}': body '{body.name()}' is above its "
                f"frame '{cfg.frame}' (on body '{frame.body().name()}'): give the body "
                "right below the sensor"
            )
        X_BS = frame.CalcPose(context, body.body_frame())
        return _Sensor(name, frame, body, X_BS, bodies)

    def _nest_sensors(self) -> list[tuple[int, int]]:
        """(outer, inner) sensor indices for every sensor directly below another (the
        innermost sensor whose subtree holds its body). Raises ValueError for two
        sensors on one body."""
        owner: dict[int, str] = {}
        for sensor in self._sensors:
            b = int(sensor.body.index())
            if b in owner:
                raise ValueError(
                    f"{_WHERE}: F/T sensors '{owner[b]}' and '{sensor.name}' have "
                    f"the same body '{sensor.body.name()}': give each sensor the body "
                    "right below it"
                )
            owner[b] = sensor.name
        subtrees = [set(sensor.bodies) for sensor in self._sensors]
        pairs = []
        for inner, sensor in enumerate(self._sensors):
            outers = [
                a
                for a, bodies in enumerate(subtrees)
                if a != inner and int(sensor.body.index()) in bodies
            ]
            if outers:  # nested subtrees: the smallest is the innermost
                pairs.append((min(outers, key=lambda a: len(subtrees[a])), inner))
        return pairs

    def _reflected_inertias(
        self, plant: MultibodyPlant, context: Context
    ) -> np.ndarray:
        by_joint = {}
        for index in plant.GetJointActuatorIndices():
            actuator = plant.get_joint_actuator(index)
            by_joint[int(actuator.joint().index())] = (
                actuator.rotor_inertia(context) * actuator.gear_ratio(context) ** 2
            )
        return np.array(
            [
                by_joint.get(int(plant.GetJointByName(j).index()), 0.0)
                for j in self._config.joints
            ]
        )

    def _find_unknown_wrench_frame(self, plant: MultibodyPlant, config):
        name = config.unknown_wrench_body
        if not name or name == self._base.name():
            return None
        if not plant.HasBodyNamed(name):
            raise KeyError(
                f"{_WHERE}: unknown-wrench body '{name}' is not a body of the plant"
            )
        body = plant.GetBodyByName(name)
        if int(body.index()) not in self._parent:
            raise ValueError(
                f"{_WHERE}: unknown-wrench body '{name}' is not in the robot"
            )
        return body.body_frame()

    def _check_rank(self, model: MultibodyPlant, frame) -> None:
        """A = [J_uᵀ Sᵀ] must have full column rank (Sec. 2.4). Checked on the internal
        model, whose root has 6 degrees of freedom for a fixed base too (the base's
        rows), at its default configuration; the sensor joints' rows are left out."""
        J_u = model.CalcJacobianSpatialVelocity(
            self._context,
            JacobianWrtVariable.kV,
            frame,
            self._zero3,
            model.world_frame(),
            frame,
        )
        columns = np.concatenate(
            [np.arange(self._root_v.start, self._root_v.stop), self._jv]
        )
        S = np.hstack([np.zeros((self._n, 6)), np.eye(self._n)])
        A = np.hstack([J_u[:, columns].T, S.T])
        rank = np.linalg.matrix_rank(A)
        if rank < A.shape[1]:
            raise ValueError(
                f"{_WHERE}: A = [J_uᵀ Sᵀ] has rank {rank} < {A.shape[1]}: the unknown "
                f"wrench on '{frame.body().name()}' and the torques are not identifiable"
            )


    # ----------------------------------------------------------------- accessors

    def plant(self) -> MultibodyPlant:
        return self._plant

    def config(self) -> TorqueEstimatorConfig:
        return self._config

    def num_joints(self) -> int:
        """n, the size of q, v, vdot and tau."""
        return self._n

    def num_sensors(self) -> int:
        """k, the number of F/T sensors (rows of `wrenches`)."""
        return len(self._sensors)

    def sensor_names(self) -> list[str]:
        """The F/T sensors, in the order of `wrenches`' rows (config.sensors')."""
        return [s.name for s in self._sensors]

    def period(self) -> float:
        """The update period (s), config.period."""
        return self._config.period

    def base_body(self) -> RigidBody:
        """The robot's base (of `plant`): its floating base or its body welded to the
        world (`is_fixed_base()`)."""
        return self._base

    def is_fixed_base(self) -> bool:
        """True if the base is welded to the world (directly or through welds)."""
        return self._fixed_base

    def has_imu(self) -> bool:
        """False for a fixed base without IMU (`step` takes None for the imu_*
        inputs)."""
        return self._has_imu

    def reads_angular_acceleration(self) -> bool:
        """False without IMU or with angular_acceleration "neglected": `step` does not
        read imu_angular_acceleration (may be None)."""
        return self._read_alpha

    def nested_sensors(self) -> dict[str, str]:
        """Each sensor nested below another: {inner name: the outer sensor's name}."""
        return {
            self._sensors[b].name: self._sensors[a].name for a, b, _, _ in self._nesting
        }

    def reflected_inertia(self) -> np.ndarray:
        """ρ² I_r of each joint (kg·m²), config.joints order (0 without actuator)."""
        return self._reflected_inertia.copy()

    def output_names(self) -> list[str]:
        """The named state arrays that are outputs, in the estimator's port order."""
        return [
            "tau",
            "unknown_wrench",
            *(f"external_wrench_{s.name}" for s in self._sensors),
        ]

    def offsets(self) -> np.ndarray:
        """(k, 6) F/T offsets in use (sensor frame, N·m and N), a copy."""
        return self._offsets.copy()

    def num_calibration_samples(self) -> int:
        return int(self.calibration[-1])

    def set_offsets(self, offsets: np.ndarray) -> None:
        """Sets the F/T offsets in use, (k, 6) in config.sensors order, sensor frames
        (N·m, N); see FloatingBaseTorqueEstimator.set_offsets."""
        k = len(self._sensors)
        value = check_vector("offsets", np.ravel(offsets), 6 * k, _WHERE)
        self.calibration[:-1] = value

    # ----------------------------------------------------------------- computation

    def _unknown_wrench_map(self, model: MultibodyPlant, frame):
        """(frame, T) for the unknown wrench of the model's frame `frame` (Sec. 2.4):
        if it is welded to the root, J_u is constant and f_u = T G_root with the
        constant 6x6 T = J_u,rootᵀ⁻¹ (then frame is None); else (frame, None) and J_u
        is computed at every update."""
        J_u = model.CalcJacobianSpatialVelocity(
            self._context,
            JacobianWrtVariable.kV,
            frame,
            self._zero3,
            model.world_frame(),
            frame,
        )
        others = np.ones(model.num_velocities(), dtype=bool)
        others[self._root_v] = False
        if np.any(J_u[:, others] != 0.0):
            return frame, None
        return None, np.linalg.inv(J_u[:, self._root_v]).T

    def step(
        self,
        t: float,
        q: np.ndarray,
        v: np.ndarray,
        vdot: np.ndarray,
        imu_linear_acceleration: np.ndarray | None,
        imu_angular_velocity: np.ndarray | None,
        imu_angular_acceleration: np.ndarray | None,
        wrenches: np.ndarray | None,
    ) -> None:
        """One update at time t (s), in place on the state. Units and frames of the
        estimator's ports: q, v, vdot (n each; rad, rad/s, rad/s²); the imu_* (3 each;
        m/s², rad/s, rad/s²), None without IMU, and imu_angular_acceleration not read
        (may be None) unless `reads_angular_acceleration()`; wrenches (k, 6), rows in
        `sensor_names()` order, each sensor's reading [torque; force] (N·m, N), None
        for k = 0. During the calibration window (config) the offsets are averaged.

        Raises:
            ValueError: an input read is not finite (named).
        """
        empty = self._empty
        imu = self._has_imu
        # The inputs into the work array, and their sum: one check for all (the other
        # entries of x and v̇ are finite).
        total = estimator_inputs(
            q,
            v,
            vdot,
            imu_linear_acceleration if imu else empty,
            imu_angular_velocity if imu else empty,
            imu_angular_acceleration if self._read_alpha else empty,
            self._raw if wrenches is None else wrenches,
            self._work,
            self._table,
        )
        if not math.isfinite(total):
            self._raise_non_finite(
                q,
                v,
                vdot,
                imu_linear_acceleration,
                imu_angular_velocity,
                imu_angular_acceleration,
                wrenches,
            )
        calibrating = (
            self._calibrates and self._calibration_begin <= t < self._calibration_end
        )
        self._evaluate(calibrating, self.state)

    def _evaluate(self, calibrating: bool, state: np.ndarray) -> None:
        """The estimate of the inputs in the work array, into `state` (the step's or
        one of its layout): Drake's calls, then `estimator_outputs`."""
        model, context = self._model, self._context
        # Step 1: the root (the IMU frame) at the identity, with the gyro's angular
        # velocity and the IMU's proper acceleration; or the fixed base at rest with
        # its constant proper acceleration (set at construction).
        model.SetPositionsAndVelocities(context, self._x)
        # M v̇ + h, without gravity (proper accelerations carry it): step 2's Σ_b Ḣ_b
        # of every sensor at once (the sensor joints' rows), and step 3's G before the
        # external wrenches.
        G = model.CalcInverseDynamics(context, self._vdot, self._no_forces)
        if self._nesting:
            for pose, (_, _, S_a, S_b) in zip(self._poses, self._nesting):
                pose[:] = model.CalcRelativeTransform(context, S_a, S_b).GetAsMatrix34()
        jacobians = self._jacobians()
        estimator_outputs(calibrating, G, jacobians, self._work, state, self._table)

    def _jacobians(self) -> tuple:
        """J_m of each sensor (and J_u if u moves), at the context's positions."""
        if not self._jacobian_args:
            return self._no_jacobians
        return tuple(starmap(self._jacobian, self._jacobian_args))

    def _raise_non_finite(self, q, v, vdot, acc, gyro, alpha, wrenches) -> None:
        """Raises ValueError naming the first input read (in port order) that is not
        finite, with its entries."""
        inputs = [("q", q), ("v", v), ("vdot", vdot)]
        if self._has_imu:
            inputs += [("imu_linear_acceleration", acc), ("imu_angular_velocity", gyro)]
        if self._read_alpha:
            inputs.append(("imu_angular_acceleration", alpha))
        for sensor, row in zip(self._sensors, self._raw):
            inputs.append((f"wrench_{sensor.name}", row))
        for name, value in inputs:
            bad = np.flatnonzero(~np.isfinite(value))
            if bad.size:
                raise ValueError(
                    f"{_WHERE}: input '{name}' is not finite at entries {bad.tolist()}"
                )
        raise ValueError(f"{_WHERE}: the inputs sum to a non-finite number")

    def estimate(
        self,
        q: np.ndarray,
        v: np.ndarray,
        vdot: np.ndarray,
        imu_linear_acceleration: np.ndarray | None,
        imu_angular_velocity: np.ndarray | None,
        imu_angular_acceleration: np.ndarray | None,
        wrenches: np.ndarray,
        offsets: np.ndarray | None = None,
    ) -> TorqueEstimate:
        """The estimate of one sample, checked and in new arrays, leaving the state
        alone: see FloatingBaseTorqueEstimator.estimate."""
        n, k = self._n, len(self._sensors)
        q = check_vector("q", q, n, _WHERE)
        v = check_vector("v", v, n, _WHERE)
        vdot = check_vector("vdot", vdot, n, _WHERE)
        imu = self._check_imu(
            imu_linear_acceleration, imu_angular_velocity, imu_angular_acceleration
        )
        raw = check_vector("wrenches", np.ravel(wrenches), 6 * k, _WHERE).reshape(k, 6)
        off = (
            np.zeros((k, 6))
            if offsets is None
            else check_vector("offsets", np.ravel(offsets), 6 * k, _WHERE).reshape(k, 6)
        )
        empty = self._empty
        gyro, alpha, acc = (
            empty if value is None else np.ascontiguousarray(value)
            for value in (imu or (None, None, None))
        )
        contiguous = np.ascontiguousarray
        estimator_inputs(
            contiguous(q),
            contiguous(v),
            contiguous(vdot),
            acc,
            gyro,
            alpha if self._read_alpha else empty,
            contiguous(raw),
            self._work,
            self._table,
        )
        # On a state of the step's layout, with the given offsets, not calibrating.
        state = np.zeros(self.state_size)
        state[self.rows("calibration")][:-1] = off.reshape(-1)
        self._evaluate(False, state)
        first = self.rows("unknown_wrench").stop
        return TorqueEstimate(
            state[:n].copy(),
            state[n : n + 6].copy(),
            state[first : first + 6 * k].reshape(k, 6).copy(),
        )

    def _check_imu(self, acc, gyro, alpha) -> tuple | None:
        """estimate's IMU arguments, checked: (gyro, α, accelerometer), α zero if
        neglected; None without IMU."""
        imu = {
            "imu_linear_acceleration": acc,
            "imu_angular_velocity": gyro,
            "imu_angular_acceleration": alpha,
        }
        if not self._has_imu:
            given = [name for name, value in imu.items() if value is not None]
            if given:
                raise ValueError(
                    f"{_WHERE}: {given} given, but the estimator has no IMU "
                    "(TorqueEstimatorConfig.imu_frame is empty): pass None"
                )
            return None
        needed = list(imu)[:2] if self._neglect_alpha else list(imu)
        absent = [name for name in needed if imu[name] is None]
        if absent:
            raise ValueError(
                f"{_WHERE}: {absent} are None, but the estimator has an IMU "
                f"('{self._config.imu_frame}')"
            )
        acc = check_vector("imu_linear_acceleration", acc, 3, _WHERE)
        gyro = check_vector("imu_angular_velocity", gyro, 3, _WHERE)
        alpha = (
            self._zero3
            if self._neglect_alpha
            else check_vector("imu_angular_acceleration", alpha, 3, _WHERE)
        )
        return gyro, alpha, acc


class FloatingBaseTorqueEstimator(StepSystem):
    """Joint torques, external wrenches and the unknown wrench of a robot, floating-base
    or welded to the world, from encoders, one IMU (optional for a fixed base) and k
    6-axis F/T sensors, possibly nested (paper Sec. 2; method in the module docstring).

    .. code-block:: text

                                   ┌─────────────────────────────┐
        q ────────────────────────►│                             ├──► tau
        v ────────────────────────►│                             ├──► unknown_wrench
        vdot ─────────────────────►│ FloatingBaseTorqueEstimator ├──► external_wrench_<s>
        imu_linear_acceleration ──►│                             │    (one per sensor s)
        imu_angular_velocity ─────►│ (imu_*: only with an IMU)   │
        imu_angular_acceleration ─►│                             │
        wrench_<s> ───────────────►│ (one per sensor s)          │
                                   └─────────────────────────────┘

    Inputs:
        q, v, vdot (n each): joint positions (rad), velocities (rad/s), accelerations
            (rad/s²), config.joints order (e.g. Savitzky-Golay estimates from encoders).
        imu_linear_acceleration (3): proper acceleration (acceleration minus gravity,
            m/s²) of the IMU frame origin, in the IMU frame: at rest it reads +g upward.
        imu_angular_velocity (3): angular velocity of the IMU body (rad/s), IMU frame.
        imu_angular_acceleration (3): its angular acceleration (rad/s², IMU frame, the
            time derivative of imu_angular_velocity). Not read when
            config.angular_acceleration is "neglected" (it may stay unconnected).
        wrench_<sensor> (6): the sensor reading [torque; force] (N·m, N): the wrench
            the bodies below the sensor exert on the body above it, about the sensor
            origin, in the sensor frame.
        The three imu_* ports exist only with an IMU (config.imu_frame not empty); a
        robot welded to the world may have none (`has_imu()`).

    Outputs (discrete state, updated every config.period; zero before the first update):
        tau (n): estimated joint torques τ̂ (N·m), config.joints order.
        unknown_wrench (6): the unknown wrench f_u [torque; force] (N·m, N) on the
            unknown-wrench link u (config.unknown_wrench_body, default the base), about
            u's origin, expressed in u's frame: the wrench that the environment exerts
            on the robot and no F/T sensor measures (e.g. a push or a string), assumed
            on u; gravity excluded (the weight is not part of it). Close to zero when
            every contact is measured (monitoring, paper Sec. 2.4). For a fixed base
            and u = the base, it is the wrench the mounting (the weld to the world)
            exerts on the base, plus any unmeasured wrench on the bodies welded to the
            base: it holds the robot, so at rest without contact its force is the
            robot's weight, upward.
        external_wrench_<sensor> (6): the compensated external wrench [torque; force]
            the environment exerts on the bodies below that sensor, about the sensor
            origin, in the sensor frame (standing still, a foot's is +z ground
            reaction). For a sensor A with sensors nested below it: on A's segment
            only, the bodies between A and those sensors (module docstring, step 2).
            τ̂ assumes it acts on the body right below the sensor.

    Offset calibration (config.offset_calibration_time = T > 0, starting at
    t0 = config.offset_calibration_start): F/T sensors drift, so their offsets are
    measured at start-up. Procedure: start the robot (or the simulation) with nothing
    touching the bodies below the sensors (robot hanging, or held with its feet and
    hands free; it may move, slow motions are compensated); wait t0 for the filters'
    windows to fill (default 0.2 s, 2.5 windows of 80 ms), then keep contact-free for
    T more seconds (e.g. 0.5 s). At every update with t0 <= t < t0 + T the estimator
    averages the compensated wrench S + ΣḢ of each sensor (Ḣ of every body below it,
    nested sensors' included), which is the offset of its reading when nothing
    touches, and uses the running average as the offset (so the external wrenches read
    ≈ 0 while calibrating); afterwards the average is frozen and subtracted from every
    reading (before the nested sensors' wrenches are taken out of the outer one's, so
    an offset stays with its sensor). Before t0 the offsets are zero. The offsets and
    the number of samples averaged are discrete state (`offsets(context)`,
    `num_calibration_samples(context)`); with T = 0 the offsets stay zero, or at the
    values given to `set_offsets` (e.g. calibrated in an earlier run, lifted).

    Errors: a NaN or infinite input raises ValueError naming the port; an unknown
    frame, body or joint name raises KeyError naming it; ValueError for a model whose
    degrees of freedom are not the base's plus config.joints, a joint that is neither
    revolute, prismatic nor a weld, a floating base without IMU, an IMU below an F/T
    sensor, an F/T sensor body that is the base, not rigidly attached to its frame or
    above it, two sensors on one body.

    The arithmetic is `TorqueEstimatorStep`'s, which this system runs on its
    context's state (a fused controller runs the same step without Drake). Allocated
    once at construction: the internal model (module docstring), one context of it and
    one MultibodyForces (zero); per update only Drake's results (an inverse dynamics, a
    Jacobian per sensor). Per update: one SetPositionsAndVelocities, one inverse
    dynamics (F/T compensation, and τ̂ by its linearity in the applied wrenches), one
    Jacobian per sensor, one relative pose per nested sensor, and a Jacobian of the
    unknown-wrench link unless it is rigidly attached to the IMU (or the fixed base
    without IMU) (scripts/bench_estimator.py measures it).
    `plant`'s default parameters (masses, inertias, rotor inertias, gear ratios) and,
    for a fixed base without IMU, its gravity and the base's default pose are read at
    construction. `plant` must be a finalized model of the robot alone: a floating
    base, or a base welded to the world (directly or through welds), only revolute,
    prismatic and weld joints besides; its force elements are ignored.
    """


    def __init__(self, plant: MultibodyPlant, config: TorqueEstimatorConfig):
        """
        Args:
            plant: a finalized MultibodyPlant holding only the robot, with a floating
                base (for HRP-2: MultibodyPlant(0.0), add_hrp2, Finalize) or welded to
                the world (a fixed base; then config.imu_frame may be empty). It must
                outlive the estimator; it is never modified.
            config: joint, frame and sensor names and options (validated here).
        """
        super().__init__()
        step = TorqueEstimatorStep(plant, config)
        n, names = step.num_joints(), step.sensor_names()
        self._q_port = self.DeclareVectorInputPort("q", n)
        self._v_port = self.DeclareVectorInputPort("v", n)
        self._vdot_port = self.DeclareVectorInputPort("vdot", n)
        self._acc_port = self._gyro_port = self._alpha_port = None
        if step.has_imu():
            self._acc_port = self.DeclareVectorInputPort("imu_linear_acceleration", 3)
            self._gyro_port = self.DeclareVectorInputPort("imu_angular_velocity", 3)
            self._alpha_port = self.DeclareVectorInputPort(
                "imu_angular_acceleration", 3
            )
        self._wrench_ports = [
            self.DeclareVectorInputPort(f"wrench_{name}", 6) for name in names
        ]
        # The readings (k, 6), rows in sensor order, that the step takes.
        self._wrenches = np.zeros((len(names), 6)) if names else None
        self._sensor_inputs = (
            list(zip(self._wrench_ports, self._wrenches)) if names else []
        )
        self._read_alpha = step.reads_angular_acceleration()
        self._declare_step_state(step)
        for name in step.output_names():
            self._declare_step_output(name)
        self.DeclarePeriodicDiscreteUpdateEvent(step.period(), 0.0, self._update)

    # ----------------------------------------------------------------- accessors

    def plant(self) -> MultibodyPlant:
        return self._step.plant()

    def config(self) -> TorqueEstimatorConfig:
        return self._step.config()

    def sensor_names(self) -> list[str]:
        return self._step.sensor_names()

    def base_body(self) -> RigidBody:
        """The robot's base (of `plant`): its floating base or its body welded to the
        world (`is_fixed_base()`)."""
        return self._step.base_body()

    def is_fixed_base(self) -> bool:
        """True if the base is welded to the world (directly or through welds)."""
        return self._step.is_fixed_base()

    def has_imu(self) -> bool:
        """False for a fixed base without IMU (no imu_* ports)."""
        return self._step.has_imu()

    def nested_sensors(self) -> dict[str, str]:
        """Each sensor nested below another: {inner name: the outer sensor's name}."""
        return self._step.nested_sensors()

    def reflected_inertia(self) -> np.ndarray:
        """ρ² I_r of each joint (kg·m²), config.joints order (0 without actuator)."""
        return self._step.reflected_inertia()

    def offsets(self, context: Context) -> np.ndarray:
        """(k, 6) F/T offsets in use (sensor frame, N·m and N), config.sensors order."""
        self._load_context(context)
        return self._step.offsets()

    def num_calibration_samples(self, context: Context) -> int:
        self._load_context(context)
        return self._step.num_calibration_samples()

    def set_offsets(self, context: Context, offsets: np.ndarray) -> None:
        """Sets the F/T offsets in use (k, 6), config.sensors order, sensor frames (N·m,
        N): e.g. offsets calibrated earlier with nothing touching the sensors (robot
        lifted) for a run that starts in contact. A calibration period
        (config.offset_calibration_time > 0) that has not started yet replaces them."""
        self._load_context(context)
        self._step.set_offsets(offsets)
        group = self.step_group("calibration")
        context.get_mutable_discrete_state(group).SetFromVector(self._step.calibration)

    def estimate(
        self,
        q: np.ndarray,
        v: np.ndarray,
        vdot: np.ndarray,
        imu_linear_acceleration: np.ndarray | None,
        imu_angular_velocity: np.ndarray | None,
        imu_angular_acceleration: np.ndarray | None,
        wrenches: np.ndarray,
        offsets: np.ndarray | None = None,
    ) -> TorqueEstimate:
        """The estimate of one sample, without a Context (e.g. on logged data with
        non-causal filters, paper Sec. 3.4.3). Same units and frames as the ports;
        `wrenches` and `offsets` are (k, 6) in config.sensors order (offsets default
        to zero). imu_angular_acceleration is ignored (may be None) in "neglected"
        mode. Without IMU (`has_imu()` False) the three imu_* arguments must be None.

        Raises:
            ValueError: a wrong size or a non-finite value, naming the argument; an
                imu_* argument None with an IMU, or given without.
        """
        return self._step.estimate(
            q,
            v,
            vdot,
            imu_linear_acceleration,
            imu_angular_velocity,
            imu_angular_acceleration,
            wrenches,
            offsets,
        )

    # ----------------------------------------------------------------- per tick

    def _update(self, context: Context, discrete_state: DiscreteValues) -> None:
        self._load(discrete_state)
        for port, row in self._sensor_inputs:
            row[:] = port.Eval(context)
        imu = self._acc_port is not None
        try:
            self._step.step(
                context.get_time(),
                self._q_port.Eval(context),
                self._v_port.Eval(context),
                self._vdot_port.Eval(context),
                self._acc_port.Eval(context) if imu else None,
                self._gyro_port.Eval(context) if imu else None,
                self._alpha_port.Eval(context) if self._read_alpha else None,
                self._wrenches,
            )
        except ValueError:
            self._check_ports(context)  # raises naming the port, if one is not finite
            raise
        self._store(discrete_state)

    def _check_ports(self, context: Context) -> None:
        """ValueError naming the first port (in port order) that is read and not
        finite (eval_finite's message: port, time, entries)."""
        ports = [self._q_port, self._v_port, self._vdot_port]
        if self._acc_port is not None:
            ports += [self._acc_port, self._gyro_port]
        if self._read_alpha:
            ports.append(self._alpha_port)
        for port in ports + self._wrench_ports:
            eval_finite(port, context, f"{_WHERE} {self.GetSystemPathname()}")


def _internal_model(
    plant: MultibodyPlant,
    context: Context,
    root_frame: object,
    sensors: list[_Sensor],
) -> tuple[MultibodyPlant, dict[int, object]]:
    """The estimator's internal model of `plant` (module docstring): its bodies (with
    their inertias in `context`), frames, joints and actuators (rotor inertias and
    gear ratios in `context`), without geometry, force elements or gravity, with
    - a massless floating root body welded to `root_frame` (the IMU frame, or the
      fixed base's frame without IMU), every joint of the robot's tree oriented away
      from it (a revolute or prismatic joint turned around keeps its q and generalized
      force with the opposite axis, a weld its inverse pose); the joints to the world
      (the base's floating joint or weld) are left out, and the bodies out of the
      robot's tree (none for a model of the robot alone) are welded to the world;
    - above each F/T sensor's body B, a massless "mount" body at B's place on the
      joint that holds B, and a 6-dof joint (QuaternionFloatingJoint) from a frame S on
      the mount to the frame S on B. At the identity (kept for ever, at rest) the model
      moves as `plant` does; the joint's generalized forces in an inverse dynamics are
      the wrench [torque about So; force] in S that the mount applies to B's subtree.

    Fills each sensor's model_* fields and rows. Returns the model (finalized) and the
    model's copy of every frame of `plant` by frame index.

    Raises:
        ValueError: a joint of `plant` that is neither revolute, prismatic nor weld
            (nor the floating joint of the base).
    """
    model, frames = _copy_bodies_and_frames(plant, context)
    # The tree rooted at the IMU's body, and the joint that holds each body.
    holder = tree_joints(plant, root_frame.body().index())
    root_instance = _add_root(model, plant, root_frame, frames, set(holder))
    by_body = {int(sensor.body.index()): sensor for sensor in sensors}
    for child, (parent_index, joint) in sorted(holder.items()):
        forward = int(joint.child_body().index()) == child
        on_parent, on_child = (
            (joint.frame_on_parent(), joint.frame_on_child())
            if forward
            else (joint.frame_on_child(), joint.frame_on_parent())
        )
        F = frames[int(on_parent.index())]
        M = frames[int(on_child.index())]
        sensor = by_body.get(child)
        if sensor is not None:
            M = _mount_sensor(model, sensor, child, on_child, root_instance)
        try:
            copy_joint(model, plant, context, joint, F, M, forward)
        except ValueError as error:
            raise ValueError(f"{_WHERE}: {error} (besides the floating base)") from None
    model.Finalize()
    for sensor in sensors:
        # QuaternionFloatingJoint velocities: [ω_FM; v_FM] in F (= S at the identity).
        sensor.rows = sensor.joint.velocity_start() + np.arange(6)
    return model, frames


def _copy_bodies_and_frames(
    plant: MultibodyPlant, context: Context
) -> tuple[MultibodyPlant, dict[int, object]]:
    """The internal model's first step: a plant without gravity holding `plant`'s model
    instances, bodies (inertias in `context`) and frames (the ephemeral ones left
    out). Returns it (not finalized) and its copy of each frame by `plant`'s frame
    index."""
    model = MultibodyPlant(0.0)
    model.mutable_gravity_field().set_gravity_vector(np.zeros(3))
    for i in range(2, plant.num_model_instances()):  # 0: world, 1: default
        model.AddModelInstance(plant.GetModelInstanceName(ModelInstanceIndex(i)))
    for i in range(1, plant.num_bodies()):
        body = plant.get_body(BodyIndex(i))
        model.AddRigidBody(
            body.name(),
            body.model_instance(),
            body.CalcSpatialInertiaInBodyFrame(context),
        )
    frames: dict[int, object] = {}
    for i in range(plant.num_frames()):
        frame = plant.get_frame(FrameIndex(i))
        if frame.is_ephemeral():
            continue  # e.g. the frames of the base's floating joint, rebuilt by Drake
        body_frame = model.get_body(frame.body().index()).body_frame()
        frames[i] = (
            body_frame
            if frame.is_body_frame()
            else model.AddFrame(
                FixedOffsetFrame(
                    frame.name(),
                    body_frame,
                    frame.GetFixedPoseInBodyFrame(),
                    frame.model_instance(),
                )
            )
        )
    return model, frames


def _add_root(
    model: MultibodyPlant,
    plant: MultibodyPlant,
    root_frame: object,
    frames: dict[int, object],
    held: set[int],
) -> ModelInstanceIndex:
    """Adds the internal model's massless floating root body, welded to the copy of
    `root_frame`, and welds to the world the bodies out of the robot's tree (neither
    the root frame's body nor one of `held`, the bodies a joint of the tree holds).
    Returns the root's model instance."""
    in_tree = held | {int(root_frame.body().index())}
    root_instance = model.AddModelInstance(_ROOT)
    root = model.AddRigidBody(_ROOT, root_instance, SpatialInertia.Zero())
    model.AddJoint(
        WeldJoint(
            f"{_ROOT}_weld",
            root.body_frame(),
            frames[int(root_frame.index())],
            RigidTransform(),
        )
    )
    for i in range(1, plant.num_bodies()):
        if i not in in_tree:  # not the robot's: keep it out of the model's dofs
            model.WeldFrames(
                model.world_frame(), model.get_body(BodyIndex(i)).body_frame()
            )
    return root_instance


def _mount_sensor(
    model: MultibodyPlant,
    sensor: _Sensor,
    child: int,
    on_child: object,
    root_instance: ModelInstanceIndex,
) -> object:
    """Hangs body B (index `child`) below F/T sensor `sensor`: a massless mount at B's
    place and a 6-dof joint from the frame S on the mount to the frame S on B. Fills
    the sensor's model_body, model_frame, joint and p_BoSo_S. Returns the mount's frame
    that the joint holding B attaches to (at `on_child`'s pose)."""
    B = model.get_body(BodyIndex(child))
    mount = model.AddRigidBody(
        f"{sensor.name}_ft_sensor_mount", root_instance, SpatialInertia.Zero()
    )
    M = model.AddFrame(
        FixedOffsetFrame(
            f"{sensor.name}_ft_sensor_mount_joint",
            mount.body_frame(),
            on_child.GetFixedPoseInBodyFrame(),
        )
    )
    sensor.model_body = B
    sensor.model_frame = model.AddFrame(
        FixedOffsetFrame(
            f"{sensor.name}_ft_sensor",
            B.body_frame(),
            sensor.X_BS,
            root_instance,
        )
    )
    S_mount = model.AddFrame(
        FixedOffsetFrame(
            f"{sensor.name}_ft_sensor_on_mount",
            mount.body_frame(),
            sensor.X_BS,
        )
    )
    sensor.joint = model.AddJoint(
        QuaternionFloatingJoint(
            f"{sensor.name}_ft_sensor_joint", S_mount, sensor.model_frame
        )
    )
    R_BS = sensor.X_BS.rotation().matrix()
    sensor.p_BoSo_S = R_BS.T @ sensor.X_BS.translation()
    return M


# --------------------------------------------------------------------- the chain


@dataclass
class EstimationChain:
    """The systems add_estimator adds.

    Attributes:
        estimator: the FloatingBaseTorqueEstimator.
        encoder_filter: Savitzky-Golay filter of the encoders (order 2): q, v, vdot.
        sensor_filter: one Savitzky-Golay filter (order 1) of [accelerometer (3); gyro
            (3); F/T sensors (6 each, config.sensors order)]: values, and the gyro's
            derivative as the angular acceleration. Without IMU it holds the F/T
            sensors only; None without IMU and F/T sensors.
        input_fault: the sum of the filters' `input_fault` (consecutive NaN or
            infinite samples they held): > 0 means the estimates rest on held data.
    """

    estimator: FloatingBaseTorqueEstimator
    encoder_filter: SavitzkyGolayFilter
    sensor_filter: SavitzkyGolayFilter | None
    input_fault: OutputPort  # (1,) consecutive bad samples held by either filter

    def delay(self) -> float:
        """Seconds between the robot state an output of the estimator describes and the
        time it is output: the filters' delay plus two periods (a sensor sample taken
        at t enters the filters at t + period, the estimator reads the filters' update
        at t + 2 periods). For the paper's N = 80 at 1 kHz: 41.5 ms."""
        return self.encoder_filter.delay() + 2 * self.encoder_filter.period()


def filter_windows(config: TorqueEstimatorConfig) -> tuple[list[int], list[int]]:
    """The windows of the two filters of the chain (`add_estimator`, the fused
    controller): one per encoder (config.joints order), and one per entry of the
    sensor filter's signal, [accelerometer (3), gyro (3) (with an IMU); each F/T
    sensor (6, config.sensors order)]."""
    encoders = [config.window_of(j) for j in config.joints]
    imu = [config.window_of("imu")] * (6 if config.imu_frame else 0)
    return encoders, imu + [config.window_of(s) for s in config.sensors for _ in range(6)]


def add_estimator(
    builder: DiagramBuilder,
    station: System,
    plant: MultibodyPlant,
    config: TorqueEstimatorConfig,
    *,
    encoders: str = "q_measured",
    accelerometer: str = "imu_linear_acceleration",
    gyroscope: str = "imu_angular_velocity",
    wrench_prefix: str = "wrench_",
    name: str = "torque_estimator",
) -> EstimationChain:
    """Adds the whole estimation chain of paper Sec. 2 to `builder` and connects it to
    the output ports of `station` (a robot diagram, simulated or real, already added to
    `builder`), with the paper's filters (Sec. 5.1): Savitzky-Golay of order 2 on the
    encoders (q, v, vdot), of order 1 on the IMU and the F/T sensors (values; the gyro's
    derivative is the angular acceleration), one window for all (config.window) or one
    per signal (config.windows), every filter evaluated at config.window's point (one
    delay everywhere).

    .. code-block:: text

        q_measured ──────────► SG order 2 ─► value, derivative, second_derivative
                                             = q, v, vdot ──────────────────┐
        imu_linear_acceleration ─┐                                          ▼
        imu_angular_velocity ────┼─► Mux ─► SG order 1 ─► value ─► Demux ─► estimator
        wrench_<s> (each) ───────┘                    └─► derivative ─► Demux ─┘
                                     (the gyro's derivative: imu_angular_acceleration)

    Without IMU (config.imu_frame empty, a fixed base) the two imu ports are neither
    read nor needed: the Mux, the order-1 filter and the value Demux carry the F/T
    sensors only, and there is no derivative Demux; without F/T sensors either, there
    is no order-1 filter at all (EstimationChain.sensor_filter is None).

    Args:
        builder: the builder that holds `station`.
        station: the system whose outputs are the robot's sensors.
        plant: the estimator's model of the robot (see FloatingBaseTorqueEstimator: a
            floating base, or welded to the world; not the station's plant, which may
            be welded or carry contact and strings).
        config: names and options; config.joints must be the order of the encoder port.
        encoders, accelerometer, gyroscope: names of the station's output ports
            (accelerometer and gyroscope only with an IMU).
        wrench_prefix: the F/T port of sensor s is wrench_prefix + s.
        name: name of the estimator; the other systems' names start with it (give
            another to add a second chain to the same builder).

    Returns:
        The added systems (their outputs are the estimator's ports).

    Raises:
        KeyError: a port the station lacks (named), an unknown frame/joint.
    """
    config.validate()
    imu_ports = [accelerometer, gyroscope] if config.imu_frame else []
    sensor_ports = imu_ports + [wrench_prefix + s for s in config.sensors]
    _check_station_ports(station, config, encoders, sensor_ports)
    estimator = builder.AddNamedSystem(name, FloatingBaseTorqueEstimator(plant, config))
    encoder_filter = _add_encoder_filter(builder, station, estimator, config, encoders, name)
    faults = [encoder_filter.GetOutputPort("input_fault")]
    sensor_filter = _add_sensor_filter(
        builder, station, estimator, config, sensor_ports, name
    )
    if sensor_filter is not None:
        faults.append(sensor_filter.GetOutputPort("input_fault"))
    fault = builder.AddNamedSystem(f"{name}_input_fault", Adder(len(faults), 1))
    for k, port in enumerate(faults):
        builder.Connect(port, fault.get_input_port(k))
    return EstimationChain(
        estimator, encoder_filter, sensor_filter, fault.get_output_port()
    )


def _check_station_ports(
    station: System, config: TorqueEstimatorConfig, encoders: str, sensor_ports: list[str]
) -> None:
    """add_estimator's first step: `station` has the encoder port, of one entry per
    joint, and every sensor port (a KeyError, a ValueError naming them otherwise)."""
    ports = [encoders] + sensor_ports
    missing = [p for p in ports if not station.HasOutputPort(p)]
    if missing:
        raise KeyError(
            f"add_estimator: station '{station.get_name()}' has no output ports {missing}"
        )
    n = len(config.joints)
    if station.GetOutputPort(encoders).size() != n:
        raise ValueError(
            f"add_estimator: port '{encoders}' has "
            f"{station.GetOutputPort(encoders).size()} entries, config.joints has {n}"
        )


def _add_encoder_filter(
    builder: DiagramBuilder,
    station: System,
    estimator: FloatingBaseTorqueEstimator,
    config: TorqueEstimatorConfig,
    encoders: str,
    name: str,
) -> SavitzkyGolayFilter:
    """Adds the encoders' Savitzky-Golay filter (order 2) between the station's port
    `encoders` and the estimator's q, v and vdot inputs; returns it."""
    encoder_windows, _ = filter_windows(config)
    encoder_filter = builder.AddNamedSystem(
        f"{name}_encoder_filter",
        SavitzkyGolayFilter(
            len(config.joints),
            encoder_windows,
            2,
            config.period,
            config.evaluation,
            span=config.span(),
        ),
    )
    builder.Connect(station.GetOutputPort(encoders), encoder_filter.get_input_port())
    for source, target in (
        ("value", "q"),
        ("derivative", "v"),
        ("second_derivative", "vdot"),
    ):
        builder.Connect(
            encoder_filter.GetOutputPort(source), estimator.GetInputPort(target)
        )
    return encoder_filter


def _add_sensor_filter(
    builder: DiagramBuilder,
    station: System,
    estimator: FloatingBaseTorqueEstimator,
    config: TorqueEstimatorConfig,
    sensor_ports: list[str],
    name: str,
) -> SavitzkyGolayFilter | None:
    """Adds the IMU's and F/T sensors' Savitzky-Golay filter (order 1) between the
    station's `sensor_ports` (accelerometer and gyroscope with an IMU, then each F/T
    sensor's) and the estimator: a Mux, the filter, a Demux of its values, and with an
    IMU a Demux of its derivatives for the gyro's (imu_angular_acceleration). Returns
    the filter, or None (and adds nothing) without any of these sensors."""
    names = list(config.sensors)
    num_imu_ports = len(sensor_ports) - len(names)
    sizes = [3] * num_imu_ports + [6] * len(names)
    if not sizes:
        return None
    _, sensor_windows = filter_windows(config)
    mux = builder.AddNamedSystem(f"{name}_sensor_mux", Multiplexer(sizes))
    for k, port in enumerate(sensor_ports):
        builder.Connect(station.GetOutputPort(port), mux.get_input_port(k))
    sensor_filter = builder.AddNamedSystem(
        f"{name}_sensor_filter",
        SavitzkyGolayFilter(
            sum(sizes),
            sensor_windows,
            1,
            config.period,
            config.evaluation,
            span=config.span(),
        ),
    )
    builder.Connect(mux.get_output_port(), sensor_filter.get_input_port())
    values = builder.AddNamedSystem(f"{name}_sensor_values", Demultiplexer(sizes))
    builder.Connect(sensor_filter.GetOutputPort("value"), values.get_input_port())
    imu_targets = ["imu_linear_acceleration", "imu_angular_velocity"]
    targets = imu_targets[:num_imu_ports] + [f"wrench_{n}" for n in names]
    for k, target in enumerate(targets):
        builder.Connect(values.get_output_port(k), estimator.GetInputPort(target))
    if num_imu_ports:
        rates = builder.AddNamedSystem(f"{name}_sensor_derivatives", Demultiplexer(sizes))
        builder.Connect(sensor_filter.GetOutputPort("derivative"), rates.get_input_port())
        builder.Connect(
            rates.get_output_port(1),
            estimator.GetInputPort("imu_angular_acceleration"),
        )
    return sensor_filter
