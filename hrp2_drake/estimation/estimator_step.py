"""`FloatingBaseTorqueEstimatorStep`: the torque estimator's per-tick arithmetic on
plain arrays (hrp2_drake.step), which `FloatingBaseTorqueEstimator` and the fused
controller run; its two numba kernels (`estimator_inputs`, `estimator_outputs`;
hrp2_drake.kernels) and their index table. The method is in `torque_estimator`'s module
docstring.
"""

import copy
import math
from itertools import starmap
from typing import NamedTuple

import numpy as np
from pydrake.math import RigidTransform
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable, MultibodyForces, RigidBody
from pydrake.systems.framework import Context

from hrp2_drake.estimation.estimator_config import TorqueEstimatorConfig
from hrp2_drake.estimation.estimator_robot import EstimatorRobot
from hrp2_drake.estimation.internal_model import ROOT, WHERE, internal_model
from hrp2_drake.kernels import kernel
from hrp2_drake.multibody import check_vector, joint_indexing
from hrp2_drake.step import Step


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


# FloatingBaseTorqueEstimatorStep's index table (`_pack`, int64): a header, then the
# index lists.
(
    _N,  # n, the joints
    _K,  # k, the F/T sensors
    _NQ,  # the internal model's positions,
    _NV,  # and velocities
    _FLAGS,  # _HAS_IMU | _READS_ALPHA | _SUBTRACTS_ROTOR | _MAPS_UNKNOWN
    ROOT_V,  # the root's velocities [ω; v] in v (the IMU frame's)
    _PAIRS,  # the number of nested (outer, inner) sensor pairs
    # Where each part of the work array starts (x = [q; v] of the model at 0):
    _W_VDOT,  # v̇ of the model (nv)
    _W_RAW,  # the F/T readings (k, 6)
    _W_TOTAL,  # F_total (k, 6)
    _W_APPLIED,  # Σ_m J_mᵀ f_m on the joints' and the root's rows (n + 6)
    _WROOT,  # G_root (6)
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
    """`FloatingBaseTorqueEstimatorStep.step`'s inputs into the work array (`_pack`'s
    layout): q, v of the joints and the gyro into x = [q; v] of the internal model, vdot
    and the IMU's α (if read) and proper acceleration into its v̇, the F/T readings (k,
    6); acc, gyro, alpha are zero-length when not read. Returns the sum of x, v̇ and the
    readings, finite exactly when every entry is (barring an overflow): the step's one
    check of its inputs. Copies only (bitwise)."""
    n = table[_N]
    k = table[_K]
    nq = table[_NQ]
    flags = table[_FLAGS]
    if q.shape[0] != n or v.shape[0] != n or vdot.shape[0] != n:
        raise ValueError(
            "FloatingBaseTorqueEstimatorStep.step: q, v and vdot need n entries each"
        )
    if wrenches.shape[0] != k or wrenches.shape[1] != 6:
        raise ValueError(
            "FloatingBaseTorqueEstimatorStep.step: wrenches must be (k, 6)"
        )
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
            raise ValueError(
                "FloatingBaseTorqueEstimatorStep.step: the IMU inputs need 3 entries"
            )
        root = table[ROOT_V]
        for i in range(3):
            work[nq + root + i] = gyro[i]
        if flags & _READS_ALPHA:
            if alpha.shape[0] != 3:
                raise ValueError(
                    "FloatingBaseTorqueEstimatorStep.step: the IMU inputs need 3 "
                    "entries"
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


# Whole: one compiled pass on the tick's arrays; a split costs calls (scripts/bench.py)
@kernel
def estimator_outputs(calibrating, G, jacobians, work, state, table):
    """`FloatingBaseTorqueEstimatorStep.step`'s arithmetic after Drake's calls (the
    method in torque_estimator's docstring, steps 2 to 4), into `state` (tau,
    unknown_wrench, the external wrenches, the calibration, in that order): from G = M
    v̇ + h of the internal model (the inverse dynamics without applied forces),
    `jacobians` (one (6, nv) J_m per sensor, in S at So, then J_u if u moves; a single
    unused one when neither), the work array (the readings, v̇, the nested pairs' poses,
    the constants) and `table` (`_pack`). With `calibrating`, one more sample of the
    offsets' running mean first.

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
    root = table[ROOT_V]
    groot = table[_WROOT]
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


class FloatingBaseTorqueEstimatorStep(Step):
    """The per-tick arithmetic of `FloatingBaseTorqueEstimator` (its docstring:
    inputs, outputs, units, offset calibration, errors; the method in torque_estimator's
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
    attached to the model's root, one more Jacobian; then a kernel (`estimator_outputs`)
    writes the whole state from their results (the method in torque_estimator's
    docstring, steps 2 to 4). For HRP-2 (4 F/T sensors, u on the torso): 6 pybind calls
    per step (the numpy version had 12: a second inverse dynamics, k SpatialForce and k
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
            raise ValueError(f"{WHERE}: the plant must be finalized")
        self._plant = plant
        self._config = copy.deepcopy(config)
        plant_context = plant.CreateDefaultContext()
        self._zero3 = np.zeros(3)
        imu, unknown_frame, nesting = self._check_robot(plant, plant_context, config)
        # The internal model, in which everything is computed (torque_estimator's
        # docstring). Its root is the IMU frame, or the fixed base's frame without IMU.
        root_frame = imu if self._has_imu else self._base.body_frame()
        model, frames = internal_model(plant, plant_context, root_frame, self._sensors)
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
        # F/T offsets (6 per sensor: each sensor's config.offset, else zero) then
        # the number of calibration samples.
        calibration = np.zeros(6 * k + 1)
        for i, sensor in enumerate(self._sensors):
            offset = config.sensors[sensor.name].offset
            if offset:
                calibration[6 * i : 6 * i + 6] = offset
        self._declare("calibration", calibration)
        self._finalize()
        self._table = self._pack()
        self._imu_offset_views(config)

    def _check_robot(
        self, plant: MultibodyPlant, plant_context: Context, config
    ) -> tuple[object, object, list[tuple[int, int]]]:
        """Finds and checks the robot (`EstimatorRobot`); returns (IMU frame or None,
        unknown-wrench frame or None for the base, the nested (outer, inner) sensor
        pairs)."""
        robot = EstimatorRobot(plant, plant_context, config)
        self._base, self._fixed_base = robot.base, robot.fixed_base
        self._indexing, self._n = robot.indexing, robot.n
        self._has_imu = robot.imu is not None
        self._sensors = robot.sensors
        self._reflected_inertia = robot.reflected_inertia
        return robot.imu, robot.unknown_frame, robot.nesting

    def _make_work_arrays(
        self, plant: MultibodyPlant, plant_context: Context, config, num_pairs: int
    ) -> None:
        """The kernels' work array and where the inputs go in it (index arrays: the
        model's order is not the joints'): x = [q; v] of the model, v̇, the F/T
        readings (k, 6), F_total (k, 6), G_root (6), the pose (3, 4) of each of the
        `num_pairs` nested sensor pairs, then constants (`_pack`); views on it."""
        model = self._model
        root = model.GetBodyByName(ROOT, model.GetModelInstanceByName(ROOT))
        start = root.floating_velocities_start_in_v()
        nq, nv = model.num_positions(), model.num_velocities()
        indexing = joint_indexing(model, config.joints)
        k = len(self._sensors)
        # x, v̇, readings, F_total, Σ J_mᵀ f_m, G_root, poses, J_u,rootᵀ⁻¹, ρ² I_r.
        sizes = [nq + nv, nv, 6 * k, 6 * k, self._n + 6, 6, 12 * num_pairs, 36, self._n]
        self._work = np.zeros(sum(sizes))
        self._work_starts = np.cumsum([0, *sizes[:-1]])
        x, vdot, raw, _, _, _, poses, _, _ = np.split(self._work, self._work_starts[1:])
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

    def _imu_offset_views(self, config: TorqueEstimatorConfig) -> None:
        """The IMU's offsets (config.imu_offset: accelerometer, gyro), subtracted
        from its readings where `estimator_inputs` puts them in the work array (the
        root's v̇ and v), or None without them."""
        self._imu_offset = None
        if not (self._has_imu and config.imu_offset):
            return
        table, offset = self._table, np.asarray(config.imu_offset, float)
        nq, root, vd = table[_NQ], table[ROOT_V], table[_W_VDOT]
        self._imu_offset = (
            (self._work[vd + root + 3 : vd + root + 6], offset[:3].copy()),
            (self._work[nq + root : nq + root + 3], offset[3:].copy()),
        )

    def _views_changed(self) -> None:
        k = len(self._sensors)
        self._offsets = self.calibration[:-1].reshape(k, 6)

    # ----------------------------------------------------------------- construction

    def _frame_jacobian(self, model: MultibodyPlant, frame) -> np.ndarray:
        """J_u: the spatial velocity Jacobian of `frame` (about its origin, expressed
        in itself) on the internal model, at the step's context."""
        return model.CalcJacobianSpatialVelocity(
            self._context,
            JacobianWrtVariable.kV,
            frame,
            self._zero3,
            model.world_frame(),
            frame,
        )

    def _check_rank(self, model: MultibodyPlant, frame) -> None:
        """A = [J_uᵀ Sᵀ] must have full column rank (Sec. 2.4). Checked on the internal
        model, whose root has 6 degrees of freedom for a fixed base too (the base's
        rows), at its default configuration; the sensor joints' rows are left out."""
        J_u = self._frame_jacobian(model, frame)
        columns = np.concatenate(
            [np.arange(self._root_v.start, self._root_v.stop), self._jv]
        )
        S = np.hstack([np.zeros((self._n, 6)), np.eye(self._n)])
        A = np.hstack([J_u[:, columns].T, S.T])
        rank = np.linalg.matrix_rank(A)
        if rank < A.shape[1]:
            raise ValueError(
                f"{WHERE}: A = [J_uᵀ Sᵀ] has rank {rank} < {A.shape[1]}: the unknown "
                f"wrench on '{frame.body().name()}' and the torques are not "
                "identifiable"
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
        value = check_vector("offsets", np.ravel(offsets), 6 * k, WHERE)
        self.calibration[:-1] = value

    # ----------------------------------------------------------------- computation

    def _unknown_wrench_map(self, model: MultibodyPlant, frame):
        """(frame, T) for the unknown wrench of the model's frame `frame` (Sec. 2.4):
        if it is welded to the root, J_u is constant and f_u = T G_root with the
        constant 6x6 T = J_u,rootᵀ⁻¹ (then frame is None); else (frame, None) and J_u
        is computed at every update."""
        J_u = self._frame_jacobian(model, frame)
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
        if self._imu_offset is not None:
            for reading, offset in self._imu_offset:
                reading -= offset
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
                    f"{WHERE}: input '{name}' is not finite at entries {bad.tolist()}"
                )
        raise ValueError(f"{WHERE}: the inputs sum to a non-finite number")

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
        q = check_vector("q", q, n, WHERE)
        v = check_vector("v", v, n, WHERE)
        vdot = check_vector("vdot", vdot, n, WHERE)
        imu = self._check_imu(
            imu_linear_acceleration, imu_angular_velocity, imu_angular_acceleration
        )
        raw = check_vector("wrenches", np.ravel(wrenches), 6 * k, WHERE).reshape(k, 6)
        off = (
            np.zeros((k, 6))
            if offsets is None
            else check_vector("offsets", np.ravel(offsets), 6 * k, WHERE).reshape(k, 6)
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
        if self._imu_offset is not None:
            for reading, offset in self._imu_offset:
                reading -= offset
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
                    f"{WHERE}: {given} given, but the estimator has no IMU "
                    "(TorqueEstimatorConfig.imu_frame is empty): pass None"
                )
            return None
        needed = list(imu)[:2] if self._neglect_alpha else list(imu)
        absent = [name for name in needed if imu[name] is None]
        if absent:
            raise ValueError(
                f"{WHERE}: {absent} are None, but the estimator has an IMU "
                f"('{self._config.imu_frame}')"
            )
        acc = check_vector("imu_linear_acceleration", acc, 3, WHERE)
        gyro = check_vector("imu_angular_velocity", gyro, 3, WHERE)
        alpha = (
            self._zero3
            if self._neglect_alpha
            else check_vector("imu_angular_acceleration", alpha, 3, WHERE)
        )
        return gyro, alpha, acc
