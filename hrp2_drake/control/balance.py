"""WholeBodyBalanceController: a floating-base robot standing on its soles, torques
from a whole-body inverse-dynamics QP with contacts (TSID's formulation, issue 29).

The QP, over x = [v̇; f] (nv generalized accelerations, then 3 force components
per sole corner, each in its sole's frame: 4 corners, 12 per sole):

    min  w_com ‖J_com v̇ + J̇_com v − a_com*‖² + w_base ‖ω̇_B − α_B*‖²
         + w_posture ‖v̇_j − a_j*‖² + w_force ‖f‖² + w_reg ‖v̇‖²
         + w_rate ‖(f − f_prev) / m‖²               (f_prev: the last tick's)
    s.t. M_b v̇ + h_b = J_fbᵀ f                       (the base's 6 rows of
                                                       M v̇ + h = Sᵀ τ + J_fᵀ f)
         J_s v̇ + J̇_s v = 0                            (each sole: 6 rows, no motion)
         −τ_max ≤ M_j v̇ + h_j − J_fjᵀ f ≤ τ_max       (τ, eliminated: its rows)
         |f_x|, |f_y| ≤ μ/√2 f_z,  f_z ≥ f_min       (each corner: a pyramid inside
                                                       the cone)
         |v̇_j| ≤ a_max                                (joint accelerations)

with M, h = C v − τ_g the robot's mass matrix and bias (rotor inertias included),
the base's rows b (6: the floating joint's) and the joints' rows j, J_f the corners'
translational Jacobians (velocities expressed in their sole frame), J_s each sole's
spatial-velocity Jacobian. The torque is recovered after the solve:
τ = M_j v̇ + h_j − J_fjᵀ f.

Why corner forces and not a 6-D wrench per sole: the centre of pressure of forces
with f_z ≥ 0 at the corners is a convex combination of the corners, so it lies
inside the sole by construction, and each corner's pyramid bounds the sole's
tangential force and its torsion with constant rows (in the sole's frame) that never
change; TSID's Contact6d does the same. The price, 12 variables per sole instead of
6, is what makes the problem about 60 variables (36 + 24 on HRP-2), the size
sot-torque-control's HRP-2 balance controller solved.

The task references (TSID's PD form; gains in 1/s², 1/s):

    a_com* = a_ref + K_p,com (p_ref − p_com) + K_d,com (v_ref − J_com v)
    α_B*   = K_p,base e_R − K_d,base ω_B      (e_R: the rotation from the base's
                                               orientation to the upright one, as
                                               sin θ · axis, in the world)
    a_j*   = K_p,post (q_ref − q_j) − K_d,post v_j

Built once, updated every tick: the program's sizes and its constant rows (the
pyramids, the bounds) are set at construction; each tick writes M, h, the Jacobians
and the references into preallocated arrays and updates the solver's coefficients
(`QpBackend.update`), warm-started from the last solution where the solver allows.

An infeasible or failed solve is a fault (`BalanceFault`): the step keeps its last
good torque (or, before any, the static torque that holds the robot still with the
least-norm contact forces) and outputs no NaN; a non-finite input is a fault too.
"""

import copy
import math
from dataclasses import dataclass, field, replace
from enum import IntEnum

import numpy as np
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import JacobianWrtVariable
from pydrake.systems.framework import Context

from hrp2_drake.description.contacts import (
    GENERIC_BALANCE,
    BalanceDescription,
    ContactsDescription,
)
from hrp2_drake.kernels import kernel
from hrp2_drake.multibody import (
    check_joint_names,
    floating_base,
    get_frame,
    joint_indexing,
)
from hrp2_drake.step import Step, StepSystem

_WHERE = "WholeBodyBalanceController"
#: The corners of a sole, 3 force components each.
_CORNERS = 4
#: BalanceConfig.force_rate_weight's default (s⁴/m²), chosen by the sweep on HRP-2
#: (docs/balance.md, "The sweep behind the defaults").
FORCE_RATE_WEIGHT = 1.2


class BalanceFault(IntEnum):
    """Why a tick's QP gave no torque (`fault` output): the last good torque is
    kept."""

    NONE = 0
    INPUT_NOT_FINITE = 1
    INFEASIBLE = 2
    SOLVER_FAILED = 3
    SOLUTION_NOT_FINITE = 4


#: Each BalanceFault in words.
BALANCE_FAULTS: dict[int, str] = {
    BalanceFault.NONE: "",
    BalanceFault.INPUT_NOT_FINITE: "an input (state or reference) is not finite",
    BalanceFault.INFEASIBLE: "the QP is infeasible",
    BalanceFault.SOLVER_FAILED: "the solver failed (iteration limit, numerics)",
    BalanceFault.SOLUTION_NOT_FINITE: "the solver returned a non-finite solution",
}


# yaml_load_typed reads the field types at run time: this module must not use
# `from __future__ import annotations`.
@dataclass
class BalanceConfig:
    """Configuration of WholeBodyBalanceController (the module docstring has the QP).

    Args:
        joints: every actuated joint of the robot, in the order of τ and q_ref (the
            description's `joints`).
        soles: the sole frames in contact (names in the description's `contacts`);
            empty: every sole of the description.
        friction: μ the QP assumes (its pyramids use μ/√2, inside the cone), at
            most the description's contacts.friction; None: the robot's (its
            description's `balance.friction`, which has no generic value).
        min_normal_force: f_min, the least normal force of each corner (N); None:
            the robot's (`balance.min_normal_force`, else 0).
        com_kp, com_kd: the CoM task's gains (1/s², 1/s); None: the robot's
            (`balance.com_kp`, `com_kd`, else 30/s² and 11/s).
        com_weight: its weight.
        base_kp, base_kd: the base orientation task's gains (1/s², 1/s).
        base_weight: its weight.
        posture_kp, posture_kd: the posture task's gains (1/s², 1/s).
        posture_weight: its weight.
        force_weight: the weight of ‖f‖² (N⁻², small: a regularisation).
        force_rate_weight: the weight of ‖(f − f_prev) / m‖² (s⁴/m²: the forces'
            change from the last tick's solution, per the robot's mass m, an
            acceleration): smooths the contact forces from tick to tick, so that
            the QP does not jump between force distributions its other tasks
            barely tell apart (docs/balance.md, "The sweep behind the defaults").
        acceleration_weight: the weight of ‖v̇‖² (small: makes the cost strictly
            convex).
        torque_limit_scale: the torque limits are this fraction of the model's
            actuator effort limits (the URDF's `effort`); 0 makes the QP infeasible
            (a test of the fault).
        acceleration_limit: |v̇_j| bound of every joint (rad/s²); sot-torque-control
            used 30.
        solver: the QP solver: "daqp" (the default, a dependency: a dense
            active-set solver warm-started from its last active set; faster than
            OSQP per solve on HRP-2, `scripts/bench_balance.py` and
            `scripts/bench.py --only balance` measure both), or pydrake's own
            "osqp" or "clarabel".

    The settings left None are the robot's: `for_robot` fills them from its
    description (`description.contacts.BalanceDescription`, `GENERIC_BALANCE`)
    before a controller is built.
    """

    joints: list[str] = field(default_factory=list)
    soles: list[str] = field(default_factory=list)
    friction: float | None = None
    min_normal_force: float | None = None
    com_kp: float | None = None
    com_kd: float | None = None
    com_weight: float = 1.0
    base_kp: float = 30.0
    base_kd: float = 11.0
    base_weight: float = 0.1
    posture_kp: float = 10.0
    posture_kd: float = 6.3
    posture_weight: float = 0.001
    force_weight: float = 1e-6
    force_rate_weight: float = FORCE_RATE_WEIGHT
    acceleration_weight: float = 1e-6
    torque_limit_scale: float = 1.0
    acceleration_limit: float = 30.0
    solver: str = "daqp"

    def validate(self) -> None:
        """Raises ValueError naming the bad field (yaml_load_typed does not call it)."""
        where = "BalanceConfig"
        if self.joints:  # (empty: the robot's, filled in where it is known)
            check_joint_names(self.joints, where)
        for name in _ROBOT_SETTINGS:
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"{where}.{name}: must be finite and >= 0, got {value}"
                )
        if self.friction is not None and not self.friction > 0:
            raise ValueError(f"{where}.friction: must be > 0, got {self.friction}")
        for name in (
            "com_weight",
            "base_kp",
            "base_kd",
            "base_weight",
            "posture_kp",
            "posture_kd",
            "posture_weight",
            "force_weight",
            "force_rate_weight",
            "acceleration_weight",
            "torque_limit_scale",
            "acceleration_limit",
        ):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(
                    f"{where}.{name}: must be finite and >= 0, got {value}"
                )
        if not self.acceleration_weight > 0:
            raise ValueError(
                f"{where}.acceleration_weight: must be > 0 (the cost must be strictly "
                f"convex), got {self.acceleration_weight}"
            )
        if self.solver not in QP_SOLVERS:
            raise ValueError(
                f"{where}.solver: '{self.solver}', expected one of {QP_SOLVERS}"
            )

    def for_robot(self, robot: BalanceDescription, where: str = "") -> "BalanceConfig":
        """A copy with the settings left None filled in from the robot's description
        (`robot`: its `balance`), else from `GENERIC_BALANCE`.

        Raises:
            ValueError: one line naming `balance.friction` (prefixed by `where`, the
                description's file) when neither this config nor the robot gives the
                friction.
        """
        given = robot.given()
        filled = {}
        for name in _ROBOT_SETTINGS:
            if getattr(self, name) is not None:
                continue
            if name in given:
                filled[name] = given[name]
            elif name in GENERIC_BALANCE:
                filled[name] = GENERIC_BALANCE[name]
            else:
                prefix = f"{where}: " if where else ""
                raise ValueError(
                    f"{prefix}balance.{name}: not given (nor BalanceConfig.{name}): "
                    "the friction the balance QP counts on is the robot's (its soles "
                    "on its floor), it has no generic value"
                )
        return replace(self, **filled)

    def unset(self) -> list[str]:
        """The robot's settings still None (`for_robot` not applied)."""
        return [name for name in _ROBOT_SETTINGS if getattr(self, name) is None]


#: BalanceConfig's settings that are the robot's when left None (`for_robot`).
_ROBOT_SETTINGS = ("friction", "min_normal_force", "com_kp", "com_kd")


class QpData:
    """One QP in the form every backend takes, in arrays allocated once:

        min ½ xᵀ H x + gᵀ x   s.t.   A_eq x = b_eq,   l ≤ A_in x ≤ u,   lo ≤ x ≤ hi

    (infinite entries of l, u, lo, hi: no bound)."""

    def __init__(self, n: int, n_eq: int, n_in: int):
        self.H = np.zeros((n, n))
        self.g = np.zeros(n)
        self.A_eq = np.zeros((n_eq, n))
        self.b_eq = np.zeros(n_eq)
        self.A_in = np.zeros((n_in, n))
        self.l_in = np.full(n_in, -np.inf)
        self.u_in = np.full(n_in, np.inf)
        self.lo = np.full(n, -np.inf)
        self.hi = np.full(n, np.inf)

    @property
    def sizes(self) -> tuple[int, int, int]:
        """(variables, equalities, inequality rows), the bounds not counted."""
        return self.H.shape[0], self.A_eq.shape[0], self.A_in.shape[0]


class QpBackend:
    """A solver holding one QP built once (`QpData`'s sizes): `update` takes the new
    coefficients, `solve` returns (fault, x), x its own array (valid until the next
    solve); warm-started from the previous solution where the solver allows."""

    name = ""

    def update(self, qp: QpData) -> None:
        raise NotImplementedError

    def solve(self) -> tuple[int, np.ndarray]:
        raise NotImplementedError


class DrakeQp(QpBackend):
    """pydrake's MathematicalProgram, built once: one quadratic cost, one linear
    equality, one linear inequality and one bounding box, whose coefficients
    `update` replaces (UpdateCoefficients on the bindings); solved by OsqpSolver
    (eps 1e-9: the base's rows of the dynamics to ~1e-8 N) or ClarabelSolver. The
    last solution is passed as the initial guess, but neither warm-starts from it
    through pydrake (on HRP-2, OSQP takes as many iterations with it as without:
    Drake sets OSQP up anew at each Solve, without the duals)."""

    def __init__(self, qp: QpData, solver: str):
        from pydrake.solvers import (
            ClarabelSolver,
            MathematicalProgram,
            OsqpSolver,
            SolverOptions,
        )

        self.name = solver
        prog = self._prog = MathematicalProgram()
        n = qp.H.shape[0]
        x = prog.NewContinuousVariables(n, "x")
        self._cost = prog.AddQuadraticCost(qp.H, qp.g, x, is_convex=True)
        self._eq = prog.AddLinearEqualityConstraint(qp.A_eq, qp.b_eq, x)
        self._in = prog.AddLinearConstraint(qp.A_in, qp.l_in, qp.u_in, x)
        self._box = prog.AddBoundingBoxConstraint(qp.lo, qp.hi, x)
        self._options = SolverOptions()
        if solver == "osqp":
            self._solver = OsqpSolver()
            # Tighter than OSQP's defaults (1e-3): forces of hundreds of N.
            for key, value in (("eps_abs", 1e-9), ("eps_rel", 1e-9)):
                self._options.SetOption(OsqpSolver.id(), key, value)
            self._options.SetOption(OsqpSolver.id(), "max_iter", 20000)
        else:
            self._solver = ClarabelSolver()
        self._x = np.zeros(n)
        self._guess = np.zeros(n)

    def update(self, qp: QpData) -> None:
        self._cost.evaluator().UpdateCoefficients(qp.H, qp.g, 0.0, True)
        self._eq.evaluator().UpdateCoefficients(qp.A_eq, qp.b_eq)
        self._in.evaluator().UpdateCoefficients(qp.A_in, qp.l_in, qp.u_in)

    def solve(self) -> tuple[int, np.ndarray]:
        from pydrake.solvers import SolutionResult

        result = self._solver.Solve(self._prog, self._guess, self._options)
        status = result.get_solution_result()
        if status == SolutionResult.kSolutionFound:
            self._x[:] = result.GetSolution()
            self._guess[:] = self._x
            return BalanceFault.NONE, self._x
        if status in (
            SolutionResult.kInfeasibleConstraints,
            SolutionResult.kInfeasibleOrUnbounded,
            SolutionResult.kDualInfeasible,
        ):
            return BalanceFault.INFEASIBLE, self._x
        return BalanceFault.SOLVER_FAILED, self._x


class DaqpQp(QpBackend):
    """daqp (a dense active-set solver, pip `daqp`; the default solver): every
    constraint as a two-sided row, the equalities immutable; the bounds as simple
    bounds; warm-started with the last solve's multipliers (`dual_start`: its
    active set). Its time on HRP-2 is mostly its setup (H's factorisation), which
    the warm start does not save (`scripts/bench_balance.py` measures both)."""

    name = "daqp"

    def __init__(self, qp: QpData):
        import daqp  # noqa: F401 (if it is missing: fail here, not per tick)

        n, n_eq, n_in = qp.sizes
        self._A = np.zeros((n_eq + n_in, n))
        self._upper = np.zeros(n + n_eq + n_in)
        self._lower = np.zeros(n + n_eq + n_in)
        self._sense = np.zeros(n + n_eq + n_in, dtype=np.int32)
        self._sense[n : n + n_eq] = 5  # active and immutable: an equality
        self._H = np.zeros((n, n))
        self._g = np.zeros(n)
        self._x = np.zeros(n)
        self._n, self._n_eq = n, n_eq
        self._dual = None  # the last good solve's multipliers

    def update(self, qp: QpData) -> None:
        n, n_eq = self._n, self._n_eq
        self._H[:] = qp.H
        self._g[:] = qp.g
        self._A[:n_eq] = qp.A_eq
        self._A[n_eq:] = qp.A_in
        big = 1e30  # daqp's infinity
        np.clip(qp.hi, -big, big, out=self._upper[:n])
        np.clip(qp.lo, -big, big, out=self._lower[:n])
        self._upper[n : n + n_eq] = qp.b_eq
        self._lower[n : n + n_eq] = qp.b_eq
        np.clip(qp.u_in, -big, big, out=self._upper[n + n_eq :])
        np.clip(qp.l_in, -big, big, out=self._lower[n + n_eq :])

    def solve(self) -> tuple[int, np.ndarray]:
        import daqp

        x, _, exitflag, info = daqp.solve(
            self._H,
            self._g,
            self._A,
            self._upper,
            self._lower,
            self._sense,
            dual_start=self._dual,
        )
        if exitflag < 0:
            self._dual = None
            if exitflag == -1:
                return BalanceFault.INFEASIBLE, self._x
            return BalanceFault.SOLVER_FAILED, self._x
        self._x[:] = x
        self._dual = info["lam"]
        return BalanceFault.NONE, self._x


#: The solvers `BalanceConfig.solver` names.
QP_SOLVERS: tuple[str, ...] = ("osqp", "clarabel", "daqp")


def make_qp_backend(qp: QpData, solver: str) -> QpBackend:
    """The backend `solver` names (QP_SOLVERS), built once on `qp`'s sizes.

    Raises:
        ValueError: an unknown solver, or a pip solver that is not installed (the
            message says how to install it).
    """
    if solver in ("osqp", "clarabel"):
        return DrakeQp(qp, solver)
    try:
        if solver == "daqp":
            return DaqpQp(qp)
    except ImportError:
        raise ValueError(
            f"BalanceConfig.solver: '{solver}' is not installed: pip install "
            f"{solver} (a dependency of hrp2_drake), or choose solver: osqp"
        ) from None
    raise ValueError(f"BalanceConfig.solver: '{solver}', expected one of {QP_SOLVERS}")


# The kernels' index table (`WholeBodyBalanceControllerStep._pack`, int64): a header,
# then the joints' positions in q and velocities in v.
(
    _NV,  # the plant's velocities
    _NJ,  # the joints, n
    _NQ,  # the plant's positions
    _BASE_Q,  # the base's quaternion [w, x, y, z] in q
    _BASE_V,  # its velocities [ω_WB; v_WBo] (in W) in v
    _NF,  # the corner forces' components
    _NS,  # the soles
    _HEADER,
) = range(8)
# The kernels' constants (`WholeBodyBalanceControllerStep._pack`, float64), then
# τ_max (n).
(
    _MASS,
    _GX,  # the gravity vector (3)
    _COM_KP,
    _COM_KD,
    _COM_W,
    _BASE_KP,
    _BASE_KD,
    _BASE_W,
    _POST_KP,
    _POST_KD,
    _POST_W,
    _RATE_W,  # force_rate_weight / m² (N⁻²)
    _CONSTANTS,
) = (0, 1, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14)


# Whole: one compiled pass on the tick's arrays; a split costs calls (scripts/bench.py)
@kernel
def balance_assemble(
    M,
    h,
    Jf,
    com,
    x,
    q_ref,
    com_ref,
    f_prev,
    constants,
    table,
    H0,
    J_com,
    a_com,
    qp_arrays,
):
    """`WholeBodyBalanceControllerStep`'s QP from Drake's terms (M, h = C v − τ_g, the
    corners' Jacobian J_f, the CoM's position) at the state x, with the references: the
    base's rows of the dynamics, the torque rows and their bounds, H and g (the module
    docstring), with the last tick's corner forces `f_prev` (NaN before a first solve:
    no force-rate term). `qp_arrays` is (H, g, A_eq, b_eq, A_in, l_in, u_in); the
    soles' contact rows are the caller's. Sums in loop order (no BLAS)."""
    H, g, A_eq, b_eq, A_in, l_in, u_in = qp_arrays
    nv, n, nq = table[_NV], table[_NJ], table[_NQ]
    bq, bv, nf = table[_BASE_Q], table[_BASE_V], table[_NF]
    jq, jv = _HEADER, _HEADER + n
    # The base's rows of M v̇ + h = Sᵀ τ + J_fᵀ f: M_b v̇ − J_fbᵀ f = −h_b.
    for r in range(6):
        for c in range(nv):
            A_eq[r, c] = M[bv + r, c]
        for k in range(nf):
            A_eq[r, nv + k] = -Jf[k, bv + r]
        b_eq[r] = -h[bv + r]
    # τ = M_j v̇ + h_j − J_fjᵀ f within ±τ_max.
    for i in range(n):
        row = table[jv + i]
        for c in range(nv):
            A_in[i, c] = M[row, c]
        for k in range(nf):
            A_in[i, nv + k] = -Jf[k, row]
        tau_max = constants[_CONSTANTS + i]
        l_in[i] = -tau_max - h[row]
        u_in[i] = tau_max - h[row]
    # The CoM: J_com = M_lin / m, J̇_com v = h_lin / m + g
    # (`WholeBodyBalanceControllerStep._cost`).
    mass = constants[_MASS]
    for r in range(3):
        jv_r = 0.0
        for c in range(nv):
            J_com[r, c] = M[bv + 3 + r, c] / mass
            jv_r += J_com[r, c] * x[nq + c]
        bias = h[bv + 3 + r] / mass + constants[_GX + r]
        a_com[r] = (
            com_ref[6 + r]
            + constants[_COM_KP] * (com_ref[r] - com[r])
            + constants[_COM_KD] * (com_ref[3 + r] - jv_r)
            - bias
        )
    w = constants[_COM_W]
    size = H.shape[0]
    for i in range(size):
        for j in range(size):
            H[i, j] = H0[i, j]
        g[i] = 0.0
    for i in range(nv):
        for j in range(nv):
            H[i, j] += w * (
                J_com[0, i] * J_com[0, j]
                + J_com[1, i] * J_com[1, j]
                + J_com[2, i] * J_com[2, j]
            )
        g[i] = -w * (
            J_com[0, i] * a_com[0] + J_com[1, i] * a_com[1] + J_com[2, i] * a_com[2]
        )
    # The base: e_R = −2 w [x, y, z] of its quaternion; ω_WB in the world.
    quaternion_w = x[bq]
    for r in range(3):
        alpha = (
            -2.0 * quaternion_w * constants[_BASE_KP] * x[bq + 1 + r]
            - constants[_BASE_KD] * x[nq + bv + r]
        )
        g[bv + r] -= constants[_BASE_W] * alpha
    # The posture.
    for i in range(n):
        q_i, v_i = x[table[jq + i]], x[nq + table[jv + i]]
        a_j = constants[_POST_KP] * (q_ref[i] - q_i) - constants[_POST_KD] * v_i
        g[table[jv + i]] -= constants[_POST_W] * a_j
    # The forces' change from the last tick's, f_prev (none before a first solve:
    # NaN).
    w = constants[_RATE_W]
    if w > 0.0 and math.isfinite(f_prev[0]):
        for k in range(nf):
            H[nv + k, nv + k] += w
            g[nv + k] -= w * f_prev[k]


@kernel
def balance_outputs(M, h, Jf, solution, corners, table, tau, vdot, forces, wrenches):
    """τ = M_j v̇ + h_j − J_fjᵀ f from a solution [v̇; f], and each sole's wrench
    [Σ p × f; Σ f] about its origin (`corners`: (soles, 4, 3), in its frame)."""
    nv, n, nf = table[_NV], table[_NJ], table[_NF]
    jv = _HEADER + n
    for c in range(nv):
        vdot[c] = solution[c]
    for k in range(nf):
        forces[k] = solution[nv + k]
    for i in range(n):
        row = table[jv + i]
        total = h[row]
        for c in range(nv):
            total += M[row, c] * vdot[c]
        for k in range(nf):
            total -= Jf[k, row] * forces[k]
        tau[i] = total
    for s in range(table[_NS]):
        for r in range(6):
            wrenches[6 * s + r] = 0.0
        for c in range(4):
            p = corners[s, c]
            f0 = forces[12 * s + 3 * c]
            f1 = forces[12 * s + 3 * c + 1]
            f2 = forces[12 * s + 3 * c + 2]
            wrenches[6 * s] += p[1] * f2 - p[2] * f1
            wrenches[6 * s + 1] += p[2] * f0 - p[0] * f2
            wrenches[6 * s + 2] += p[0] * f1 - p[1] * f0
            wrenches[6 * s + 3] += f0
            wrenches[6 * s + 4] += f1
            wrenches[6 * s + 5] += f2


class WholeBodyBalanceControllerStep(Step):
    """The per-tick arithmetic of WholeBodyBalanceController (the module docstring
    has the QP; the class docstring the ports, units and frames), written once for
    its LeafSystem and a fused controller.

    State (zero at construction but `fault`):
        tau_desired (n, N·m, config.joints order): τ of the last good solve (or the
            static fallback, see `BalanceFault`).
        vdot (nv): v̇ of that solve (the plant's velocity order).
        contact_forces (12 per sole): each corner's force [f_x, f_y, f_z] (N) in
            its sole's frame, corners in `SoleDescription.corners` order, soles in
            `soles()` order.
        sole_wrenches (6 per sole): each sole's wrench [torque; force] (N·m, N)
            about its frame's origin, in its frame (what the ground exerts).
        com (3): the CoM's position in the world (m) at the last tick.
        fault (1): the last tick's `BalanceFault` (0: solved).
        fault_count (1): ticks with a fault since the start.
        solved (1): 1 once a solve succeeded (the fallback keeps that torque).

    Per tick: one private context of the plant; Drake's calls: the state, the mass
    matrix, the bias and gravity terms, per sole its spatial Jacobian, bias
    acceleration and corner Jacobian, the CoM's position (11 on two soles); then
    a kernel (`balance_assemble`) rewrites the QP's arrays in place, the backend's
    coefficients are updated (never rebuilt), one solve, and a kernel
    (`balance_outputs`) writes τ and the wrenches. A tick allocates only what
    Drake's bindings and the solver's return.
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        config: BalanceConfig,
        contacts: ContactsDescription,
    ):
        """
        Args:
            plant: a finalized continuous MultibodyPlant of the robot alone, with one
                floating base (e.g. `RobotDescription.make_plant()`); it must outlive
                the step and is never modified.
            config: joints, tasks, limits, solver (validated here).
            contacts: the description's soles and friction.

        Raises:
            ValueError: a bad config or contacts description, a friction above the
                description's, a plant whose
                one-dof joints are not all in config.joints, a sole without its
                rectangle, a pip solver not installed.
            KeyError: an unknown joint or sole frame.
        """
        super().__init__()
        config.validate()
        if not config.joints:
            raise ValueError("BalanceConfig.joints is empty: list every joint")
        if config.unset():
            raise ValueError(
                f"BalanceConfig: {config.unset()} unset (None: the robot's): fill them "
                "from its description first (BalanceConfig.for_robot)"
            )
        contacts.validate()
        if not plant.is_finalized():
            raise ValueError(f"{_WHERE}: the plant must be finalized")
        self._plant, self._config = plant, config
        self._context = plant.CreateDefaultContext()
        contacts.check_model(plant)
        base = floating_base(plant, _WHERE, quaternion=True)
        self._indexing = joint_indexing(plant, config.joints)
        n = self._n = self._indexing.size
        nv = self._nv = plant.num_velocities()
        if nv != 6 + n:
            raise ValueError(
                f"BalanceConfig.joints: {n} joints, but the plant has {nv - 6} joint "
                "velocities: every joint must be listed (and actuated)"
            )
        self._soles = list(config.soles or contacts.soles)
        if not self._soles:
            raise ValueError(
                f"{_WHERE}: no soles (the description's contacts is empty)"
            )
        missing = [s for s in self._soles if s not in contacts.soles]
        if missing:
            raise ValueError(
                f"BalanceConfig.soles: {missing} have no rectangle in the "
                f"description's contacts.soles {sorted(contacts.soles)}"
            )
        if config.friction > contacts.friction:
            raise ValueError(
                f"BalanceConfig.friction: {config.friction} exceeds the description's "
                f"contacts.friction {contacts.friction}: the QP would count on "
                "friction the ground does not give"
            )
        self._frames = [get_frame(plant, s, "sole frame") for s in self._soles]
        self._corners = [contacts.soles[s].corners() for s in self._soles]
        self._base_q = base.floating_positions_start()
        self._base_v = base.floating_velocities_start_in_v()
        self._tau_max = self._effort_limits() * config.torque_limit_scale
        self._make_qp()
        ns = len(self._soles)
        self._declare("tau_desired", np.zeros(n))
        self._declare("vdot", np.zeros(nv))
        self._declare("contact_forces", np.zeros(3 * _CORNERS * ns))
        self._declare("sole_wrenches", np.zeros(6 * ns))
        self._declare("com", np.zeros(3))
        self._declare("fault", [float(BalanceFault.NONE)])
        self._declare("fault_count", [0.0])
        self._declare("solved", [0.0])
        self._finalize()
        self._backend = make_qp_backend(self.qp, config.solver)

    def _effort_limits(self) -> np.ndarray:
        """The actuators' effort limits (N·m), config.joints order (inf if none)."""
        from pydrake.multibody.tree import JointActuatorIndex

        limits = np.full(self._n, np.inf)
        for i, u in enumerate(self._indexing.u):
            if u < 0:
                name = self._indexing.names[i]
                raise ValueError(f"BalanceConfig.joints: '{name}' has no actuator")
            for index in self._plant.GetJointActuatorIndices():
                actuator = self._plant.get_joint_actuator(JointActuatorIndex(index))
                if actuator.input_start() == u:
                    limits[i] = actuator.effort_limit()
        return limits

    def _make_qp(self) -> None:
        """The QP's arrays, sizes fixed, and its constant rows: the pyramids, the
        bounds, the constant part of the cost."""
        config, n, nv = self._config, self._n, self._nv
        ns = len(self._soles)
        nf = 3 * _CORNERS * ns
        self._nf = nf
        n_in = n + 4 * _CORNERS * ns
        qp = self.qp = QpData(nv + nf, 6 + 6 * ns, n_in)
        # Each corner's pyramid (its force in its sole's frame): ±f_x, ±f_y ≤ μ' f_z.
        mu = config.friction / math.sqrt(2.0)
        for c in range(_CORNERS * ns):
            col = nv + 3 * c
            for k, (axis, sign) in enumerate(((0, 1), (0, -1), (1, 1), (1, -1))):
                row = n + 4 * c + k
                qp.A_in[row, col + axis] = sign
                qp.A_in[row, col + 2] = -mu
                qp.u_in[row] = 0.0
        qp.lo[nv + 2 : nv + nf : 3] = config.min_normal_force
        jv = self._indexing.v
        qp.lo[jv] = -config.acceleration_limit
        qp.hi[jv] = config.acceleration_limit
        # The cost's constant part: base orientation, posture, regularisations.
        self._H0 = np.zeros_like(qp.H)
        diagonal = np.full(nv + nf, config.force_weight)
        diagonal[:nv] = config.acceleration_weight
        diagonal[self._base_v : self._base_v + 3] += config.base_weight
        diagonal[jv] += config.posture_weight
        self._H0[np.diag_indices(nv + nf)] = diagonal
        # Work arrays, allocated once.
        self._x = np.zeros(self._plant.num_positions() + nv)
        self._Jf = np.zeros((nf, nv))
        self._M = np.zeros((nv, nv))
        self._h = np.zeros(nv)
        self._a_com = np.zeros(3)
        self._J_com = np.zeros((3, nv))
        self._zero3 = np.zeros(3)
        self._no_forces = np.full(nf, np.nan)  # (before a first solve)
        self._world = self._plant.world_frame()
        self._corner_array = np.array(self._corners)
        self._qp_arrays = (qp.H, qp.g, qp.A_eq, qp.b_eq, qp.A_in, qp.l_in, qp.u_in)
        self._table, self._constants = self._pack()

    def _pack(self) -> tuple[np.ndarray, np.ndarray]:
        """The kernels' index table (int64) and constants (float64)."""
        plant, config = self._plant, self._config
        header = [
            self._nv,
            self._n,
            plant.num_positions(),
            self._base_q,
            self._base_v,
            self._nf,
            len(self._soles),
        ]
        assert len(header) == _HEADER
        table = np.concatenate([header, self._indexing.q, self._indexing.v])
        constants = [
            plant.CalcTotalMass(self._context),
            *plant.gravity_field().gravity_vector(),
            config.com_kp,
            config.com_kd,
            config.com_weight,
            config.base_kp,
            config.base_kd,
            config.base_weight,
            config.posture_kp,
            config.posture_kd,
            config.posture_weight,
            config.force_rate_weight / plant.CalcTotalMass(self._context) ** 2,
        ]
        assert len(constants) == _CONSTANTS
        return table.astype(np.int64), np.r_[constants, self._tau_max]

    def warm_up(self) -> None:
        """Compiles (or loads) the two kernels on copies of the step's arrays."""
        x = np.zeros_like(self._x)
        x[self._base_q] = 1.0
        qp = copy.deepcopy(self.qp)
        arrays = (qp.H, qp.g, qp.A_eq, qp.b_eq, qp.A_in, qp.l_in, qp.u_in)
        balance_assemble(
            self._M,
            self._h,
            self._Jf,
            self._zero3,
            x,
            np.zeros(self._n),
            np.zeros(9),
            np.zeros(self._nf),
            self._constants,
            self._table,
            self._H0,
            self._J_com.copy(),
            self._a_com.copy(),
            arrays,
        )
        state = self.state.copy()
        balance_outputs(
            self._M,
            self._h,
            self._Jf,
            np.zeros(self._nv + self._nf),
            self._corner_array,
            self._table,
            *self._output_views(state),
        )

    def _output_views(self, state: np.ndarray) -> tuple[np.ndarray, ...]:
        """τ, v̇, the corner forces and the soles' wrenches: views on `state`."""
        return tuple(
            state[self.rows(name)]
            for name in ("tau_desired", "vdot", "contact_forces", "sole_wrenches")
        )

    # ----------------------------------------------------------------- accessors

    def plant(self) -> MultibodyPlant:
        return self._plant

    def config(self) -> BalanceConfig:
        return self._config

    def soles(self) -> list[str]:
        return list(self._soles)

    def joint_names(self) -> tuple[str, ...]:
        return self._indexing.names

    def torque_limits(self) -> np.ndarray:
        """τ_max (N·m), config.joints order (a copy)."""
        return self._tau_max.copy()

    def sizes(self) -> tuple[int, int, int, int]:
        """(variables, equalities, inequality rows, bounded variables)."""
        qp = self.qp
        bounded = int(np.count_nonzero(np.isfinite(qp.lo) | np.isfinite(qp.hi)))
        return (*qp.sizes, bounded)

    # ----------------------------------------------------------------- per tick

    def step(
        self, t: float, state: np.ndarray, q_ref: np.ndarray, com_ref: np.ndarray
    ) -> int:
        """One tick: the QP at the plant state `state` ([q; v], the plant's order),
        the posture reference `q_ref` (n, rad, config.joints order) and the CoM's
        reference `com_ref` (9: position, velocity, acceleration in the world, m,
        m/s, m/s²). Returns this tick's BalanceFault (0: solved); the state holds
        the result (the module docstring says what a fault keeps).
        """
        if not math.isfinite(state.sum() + q_ref.sum() + com_ref.sum()):
            return self._fault(BalanceFault.INPUT_NOT_FINITE)
        self._x[:] = state
        self._assemble(q_ref, com_ref)
        self._backend.update(self.qp)
        fault, x = self._backend.solve()
        if fault == BalanceFault.NONE and not math.isfinite(x.sum()):
            fault = BalanceFault.SOLUTION_NOT_FINITE
        if fault != BalanceFault.NONE:
            return self._fault(fault)
        self._accept(x)
        self.solved[0] = 1.0
        self.fault[0] = BalanceFault.NONE
        return BalanceFault.NONE

    def _assemble(self, q_ref: np.ndarray, com_ref: np.ndarray) -> None:
        """Drake's terms at the state in self._x, written into the QP's arrays: the
        soles' rows here, the rest by `balance_assemble`.

        The CoM's Jacobian and bias come from the base's translational rows of
        M v̇ + C v (the robot's linear momentum rate, m a_com, with the base's
        velocity in the world): J_com = M_lin / m and J̇_com v = (C v)_lin / m =
        (h_lin + m g) / m (g the gravity vector), equal to Drake's
        CalcJacobianCenterOfMassTranslationalVelocity and
        CalcBiasCenterOfMassTranslationalAcceleration to rounding (2e-16; the
        latter is a slow call on HRP-2, which this spares)."""
        plant, context = self._plant, self._context
        qp, nv = self.qp, self._nv
        kV, world = JacobianWrtVariable.kV, self._world
        plant.SetPositionsAndVelocities(context, self._x)
        # Into the step's own C-ordered M (Drake returns a column-major one): the
        # kernels see the array types `warm_up` compiled them for.
        M = self._M
        M[:] = plant.CalcMassMatrix(context)
        h = plant.CalcBiasTerm(context)
        h -= plant.CalcGravityGeneralizedForces(context)
        self._h = h
        for k, (frame, corners) in enumerate(zip(self._frames, self._corners)):
            rows = slice(6 + 6 * k, 12 + 6 * k)
            qp.A_eq[rows, :nv] = plant.CalcJacobianSpatialVelocity(
                context, kV, frame, self._zero3, world, world
            )
            bias = plant.CalcBiasSpatialAcceleration(
                context, kV, frame, self._zero3, world, world
            )
            qp.b_eq[rows] = bias.get_coeffs()
            np.negative(qp.b_eq[rows], out=qp.b_eq[rows])
            self._Jf[12 * k : 12 * k + 12] = plant.CalcJacobianTranslationalVelocity(
                context, kV, frame, corners.T, world, frame
            )
        com = plant.CalcCenterOfMassPositionInWorld(context)
        self.com[:] = com
        balance_assemble(
            M,
            h,
            self._Jf,
            com,
            self._x,
            q_ref,
            com_ref,
            self.contact_forces if self.solved[0] else self._no_forces,
            self._constants,
            self._table,
            self._H0,
            self._J_com,
            self._a_com,
            self._qp_arrays,
        )

    def _accept(self, solution: np.ndarray) -> None:
        """τ from a solution [v̇; f] (its joint rows) and the soles' wrenches."""
        balance_outputs(
            self._M,
            self._h,
            self._Jf,
            solution,
            self._corner_array,
            self._table,
            self.tau_desired,
            self.vdot,
            self.contact_forces,
            self.sole_wrenches,
        )

    def _fault(self, fault: int) -> int:
        """A fault: counted; τ stays the last good one, or, before any, the static
        torque (v̇ = 0, least-norm contact forces on the base's rows) of this tick's
        model (zero if its state was not finite)."""
        self.fault[0] = fault
        self.fault_count[0] += 1.0
        if self.solved[0] == 0.0:
            self._static_fallback(fault == BalanceFault.INPUT_NOT_FINITE)
        return fault

    def _static_fallback(self, no_model: bool) -> None:
        if no_model:
            self.tau_desired[:] = 0.0
            return
        b = slice(self._base_v, self._base_v + 6)
        f = np.linalg.lstsq(self._Jf[:, b].T, -self.qp.b_eq[:6], rcond=None)[0]
        self._accept(np.r_[np.zeros(self._nv), f])


class WholeBodyBalanceController(StepSystem):
    """Joint torques that keep a floating-base robot balanced on its soles: the
    whole-body inverse-dynamics QP with contacts of the module docstring.

    .. code-block:: text

                    ┌────────────────────────────┐
        state ─────►│                            ├──► tau_desired
        q_ref ─────►│ WholeBodyBalanceController ├──► vdot
        com_ref ───►│                            ├──► contact_forces
                    │                            ├──► sole_wrenches
                    │                            ├──► com
                    │                            ├──► fault
                    │                            ├──► fault_count
                    └────────────────────────────┘

    Inputs:
        state (nq + nv): the robot's [q; v] in the plant's order (its floating
            base's quaternion, position, ω and velocity in the world): in
            simulation the plant's state port; on a robot, an estimate.
        q_ref (n, rad): the posture task's reference, config.joints order.
        com_ref (9): the CoM's reference position, velocity and acceleration in the
            world (m, m/s, m/s²).

    Outputs (the tick of the inputs held now, direct feedthrough, committed every
    period; see `WholeBodyBalanceControllerStep`):
        tau_desired (n, N·m, config.joints order), vdot (nv), contact_forces (12
        per sole, N, each corner's force in its sole's frame), sole_wrenches (6 per
        sole, [torque; force] about the sole frame's origin, in it), com (3, m),
        fault (1, the last tick's `BalanceFault`), fault_count (1).

    Errors: a non-finite input, an infeasible or failed solve is a fault, never an
    exception and never a NaN output: the torque stays the last good one (or the
    static one before any); `fault` says why, for a supervisor to ramp to
    position control.
    """

    def __init__(
        self,
        plant: MultibodyPlant,
        config: BalanceConfig,
        contacts: ContactsDescription,
        period: float,
        lead: float = 0.0,
    ):
        """
        Args:
            plant, config, contacts: as `WholeBodyBalanceControllerStep`'s.
            period: the control period (s).
            lead: the samples arrive this long (s) before each multiple of the
                period (`StepSystem`: the commits follow the sampler).
        """
        super().__init__()
        step = WholeBodyBalanceControllerStep(plant, config, contacts)
        n = len(config.joints)
        self._state = self.DeclareVectorInputPort(
            "state", plant.num_positions() + plant.num_velocities()
        )
        self._q_ref = self.DeclareVectorInputPort("q_ref", n)
        self._com_ref = self.DeclareVectorInputPort("com_ref", 9)
        self._declare_step_state(step)
        for name in (
            "tau_desired",
            "vdot",
            "contact_forces",
            "sole_wrenches",
            "com",
            "fault",
            "fault_count",
        ):
            self._declare_step_output(name)
        self._declare_commit(period, lead)

    def step(self) -> WholeBodyBalanceControllerStep:
        return self._step

    def _tick(self, context: Context, t: float) -> None:
        self._step.step(
            t,
            self._state.Eval(context),
            self._q_ref.Eval(context),
            self._com_ref.Eval(context),
        )
