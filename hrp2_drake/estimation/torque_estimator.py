"""FloatingBaseTorqueEstimator: joint torques of a robot, floating-base or welded to the
world, from encoders, one IMU (optional for a fixed base) and 6-axis F/T sensors (paper
Sec. 2). This module is the LeafSystem and the method; the rest of the estimator lives
beside it, one concern a module:

- estimator_config.py: TorqueEstimatorConfig, `estimator_config`, the chain's filter
  windows and its delay (`estimation_delay`);
- estimator_robot.py: the robot found and checked on the plant (`EstimatorRobot`);
- internal_model.py: the internal model (below) built from the plant;
- estimator_step.py: `FloatingBaseTorqueEstimatorStep`, the per-tick arithmetic on plain
  arrays (hrp2_drake.step) and its numba kernels, which this LeafSystem and the fused
  controller run;
- estimation_chain.py: `add_estimator`, which wires the whole estimation chain
  (Savitzky-Golay filters + estimator) to a robot diagram.

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
   the unknown wrench f_u on one link u (the base by default, or a chosen link such as
   the torso) and τ. A = [J_uᵀ Sᵀ] is square; it is checked to have full column rank at
   construction (it always has for a tree: its root rows hold the invertible 6x6
   J_u,rootᵀ), so the least-squares solution is exact: f_u = J_u,root⁻ᵀ G_root, τ =
   G_joints − J_u,jointsᵀ f_u. With u on the IMU's body (the torso for HRP-2, the
   paper's choice) J_u is constant and J_u,joints = 0, so τ = S G; the estimate does not
   depend on which body is the model's base, so for u = the robot's base this is eq. 2.
   For a fixed base the model's root keeps its 6 degrees of freedom: f_u on the base is
   then the wrench the mounting exerts on it.

The internal model is a copy of the plant's bodies (inertias), frames, joints (revolute,
prismatic, welds) and actuators (rotor inertia, gear ratio), re-rooted at a massless
body welded to the IMU frame (or to the fixed base's frame without IMU; a revolute or
prismatic joint turned around keeps its q and its generalized force with the opposite
axis), plus one mount and one 6-dof joint per F/T sensor; the joint that attaches the
robot to the world (floating or weld) is not copied. Per update, the Drake calls: one
SetPositionsAndVelocities, one inverse dynamics, one Jacobian per F/T sensor (plus one
when the unknown-wrench link moves relative to the IMU, and one relative pose per nested
sensor); the arithmetic around them is two numba kernels (`estimator_inputs`,
`estimator_outputs`; hrp2_drake.kernels). That is what makes the Python estimator run at
1 kHz with room to spare (scripts/bench_estimator.py).

Reflected rotor inertia: the model's actuators may carry a rotor inertia I_r and a gear
ratio ρ (Drake adds ρ² I_r to the joint's diagonal of the mass matrix). With
`include_rotor_inertia` (default) τ̂ includes it, which is the torque the actuator
applies on the joint when the plant's mass matrix includes it (as in our simulated
HRP-2); without, ρ² I_r q̈ is removed from each joint's torque.

Only rigid-body dynamics enter the internal model: its force elements (joint damping,
springs) are not used and its gravity is off (the plant's gravity enters only as a fixed
base's proper acceleration without IMU); τ̂ is the torque the actuators transmit.
"""

import numpy as np
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import RigidBody
from pydrake.systems.framework import Context

from hrp2_drake.estimation.estimator_config import TorqueEstimatorConfig
from hrp2_drake.estimation.estimator_step import (
    FloatingBaseTorqueEstimatorStep,
    TorqueEstimate,
)
from hrp2_drake.estimation.internal_model import WHERE
from hrp2_drake.multibody import eval_finite
from hrp2_drake.step import StepSystem


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

    Outputs (the tick of the inputs held now, direct feedthrough; committed every
    config.period, `hrp2_drake.step.StepSystem`):
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
    `num_calibration_samples(context)`); with T = 0 the offsets stay at the sensors'
    `offset` (config.sensors; zero if none given), or at the values given to
    `set_offsets` (e.g. calibrated in an earlier run, lifted). The IMU's offsets
    (config.imu_offset, found standing still) are subtracted from its readings.

    Errors: a NaN or infinite input raises ValueError naming the port; an unknown
    frame, body or joint name raises KeyError naming it; ValueError for a model whose
    degrees of freedom are not the base's plus config.joints, a joint that is neither
    revolute, prismatic nor a weld, a floating base without IMU, an IMU below an F/T
    sensor, an F/T sensor body that is the base, not rigidly attached to its frame or
    above it, two sensors on one body.

    The arithmetic is `FloatingBaseTorqueEstimatorStep`'s, which this system runs on its
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

    def __init__(
        self, plant: MultibodyPlant, config: TorqueEstimatorConfig, lead: float = 0.0
    ):
        """
        Args:
            plant: a finalized MultibodyPlant holding only the robot, with a floating
                base (for HRP-2: MultibodyPlant(0.0), add_hrp2, Finalize) or welded to
                the world (a fixed base; then config.imu_frame may be empty). It must
                outlive the estimator; it is never modified.
            config: joint, frame and sensor names and options (validated here).
            lead: the samples arrive this long (s) before each multiple of the
                period (`StepSystem`: the commits follow the sampler).
        """
        super().__init__()
        step = FloatingBaseTorqueEstimatorStep(plant, config)
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
        self._declare_commit(step.period(), lead)

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

    def _tick(self, context: Context, t: float) -> None:
        for port, row in self._sensor_inputs:
            row[:] = port.Eval(context)
        imu = self._acc_port is not None
        try:
            self._step.step(
                t,
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

    def _check_ports(self, context: Context) -> None:
        """ValueError naming the first port (in port order) that is read and not
        finite (eval_finite's message: port, time, entries)."""
        ports = [self._q_port, self._v_port, self._vdot_port]
        if self._acc_port is not None:
            ports += [self._acc_port, self._gyro_port]
        if self._read_alpha:
            ports.append(self._alpha_port)
        for port in ports + self._wrench_ports:
            eval_finite(port, context, f"{WHERE} {self.GetSystemPathname()}")
