#!/usr/bin/env python3
"""The whole-body balance QP's solve on a robot standing on its soles (--robot: a
robot description with contacts; default HRP-2), per solver, against Drake's own
`CalcInverseDynamics` on the full robot in the same run (issue 29: choose the solver
by measurement).

The robot in double support (HRP-2: 60 variables, 18 equalities, 62 inequality rows and
38 bounds: `WholeBodyBalanceControllerStep.sizes`), at states of a smooth 1 kHz sequence
around the standing pose (HRP-2: half-sitting): every joint oscillating by a few 0.01
rad at 0.5-2 Hz with its velocity, the CoM's reference 2 cm to the left. One
`WholeBodyBalanceControllerStep` built once; per tick, timed: the rest of the step
(Drake's terms and the kernels that assemble the QP and write τ), each solver's solve on
the same QP (the coefficients' update and the solve: `QpBackend.update` + `solve`; each
solver keeps its own warm start), and one `CalcInverseDynamics` (gravity included) of
the full floating robot (HRP-2: 36 velocities) at the same state, the unit of the
ratios: every time of a tick is taken under the same load. A solver's step is the rest
plus its solve. Also per tick, the QP's input: the base's state from the soles'
kinematics (`FloatingBaseFromSolesStep.step`, the soles where they stood) from the same
joint angles and velocities. The garbage collector is frozen and disabled, as in the
control loop.

Solvers: pydrake's OsqpSolver and ClarabelSolver (MathematicalProgram built once,
UpdateCoefficients on the bindings, the last solution as initial guess), the pip
package daqp (a dependency, the default), and, only here, the pip packages proxsuite
(dense ProxQP, warm-started), osqp (its own workspace, warm-started) and quadprog
(cold, dense). A solver not installed is skipped.

With --closed-loop, the QP in its place instead: the fused balance controller on the
simulated standing robot (`bench_closed_loop`; what `scripts/bench.py --only
balance` reports): the QP's solve and the whole tick, per solver: daqp (the
default) and pydrake's OSQP.

    python scripts/bench_balance.py [--robot R] [--ticks 2000] [--solvers osqp,daqp]
    python scripts/bench_balance.py [--robot R] --closed-loop [--duration 2]
"""

import argparse
import gc
import sys
import time

import numpy as np

DRAKE_AND_OPTIONAL = ("osqp", "clarabel", "daqp")
BENCH_ONLY = ("proxsuite", "osqp_pip", "quadprog")


class PipOsqp:
    """osqp (pip) on the QP's dense pattern, set up once, updated, warm-started."""

    name = "osqp_pip"

    def __init__(self, qp):
        import osqp
        from scipy import sparse

        n, n_eq, n_in = qp.sizes
        self._rows, self._cols = np.triu_indices(n)
        order = np.lexsort((self._rows, self._cols))  # CSC: by column, then row
        self._rows, self._cols = self._rows[order], self._cols[order]
        ones = np.ones(self._rows.size)
        P = sparse.csc_matrix((ones, (self._rows, self._cols)), (n, n))
        self._A = np.zeros((n_eq + n_in + n, n))
        self._A[n_eq + n_in :] = np.eye(n)
        self._l = np.zeros(n_eq + n_in + n)
        self._u = np.zeros(n_eq + n_in + n)
        self._fill(qp)
        A = sparse.csc_matrix(np.ones_like(self._A))
        self._solver = osqp.OSQP()
        self._solver.setup(
            P,
            qp.g,
            A,
            self._l,
            self._u,
            eps_abs=1e-9,
            eps_rel=1e-9,
            verbose=False,
            polishing=True,
            max_iter=20000,
        )
        self._P = P
        self._x = np.zeros(n)

    def _fill(self, qp):
        n_eq = qp.A_eq.shape[0]
        n_in = qp.A_in.shape[0]
        self._A[:n_eq] = qp.A_eq
        self._A[n_eq : n_eq + n_in] = qp.A_in
        big = 1e30
        self._l[:n_eq] = self._u[:n_eq] = qp.b_eq
        self._l[n_eq : n_eq + n_in] = np.clip(qp.l_in, -big, big)
        self._u[n_eq : n_eq + n_in] = np.clip(qp.u_in, -big, big)
        self._l[n_eq + n_in :] = np.clip(qp.lo, -big, big)
        self._u[n_eq + n_in :] = np.clip(qp.hi, -big, big)

    def update(self, qp):
        self._fill(qp)
        self._solver.update(
            q=qp.g,
            l=self._l,
            u=self._u,
            Px=qp.H[self._rows, self._cols],
            Ax=self._A.reshape(-1, order="F"),
        )

    def solve(self):
        result = self._solver.solve()
        ok = "solved" in str(result.info.status).lower()
        if ok:
            self._x[:] = result.x
        return (0 if ok else 3), self._x


class Quadprog:
    """quadprog (pip, Goldfarb-Idnani, dense, no warm start): the equalities first,
    every finite one-sided bound as a ≥ row."""

    name = "quadprog"

    def __init__(self, qp):
        self._x = np.zeros(qp.sizes[0])

    def update(self, qp):
        n = qp.sizes[0]
        eye = np.eye(n)
        rows, bounds = [qp.A_eq], [qp.b_eq]
        for A, low, high in ((qp.A_in, qp.l_in, qp.u_in), (eye, qp.lo, qp.hi)):
            finite = np.isfinite(low)
            rows.append(A[finite])
            bounds.append(low[finite])
            finite = np.isfinite(high)
            rows.append(-A[finite])
            bounds.append(-high[finite])
        self._C = np.vstack(rows).T.copy()
        self._b = np.concatenate(bounds)
        self._H, self._g, self._meq = qp.H, qp.g, qp.A_eq.shape[0]

    def solve(self):
        import quadprog

        try:
            x = quadprog.solve_qp(self._H, -self._g, self._C, self._b, self._meq)[0]
        except ValueError:
            return 2, self._x
        self._x[:] = x
        return 0, self._x


class ProxsuiteQp:
    """proxsuite's dense ProxQP (pip `proxsuite`), built once with box
    constraints, warm-started from its previous result."""

    name = "proxsuite"

    def __init__(self, qp):
        from proxsuite import proxqp

        n, n_eq, n_in = qp.sizes
        self._qp = proxqp.dense.QP(n, n_eq, n_in, True)
        self._qp.settings.eps_abs = 1e-8
        self._qp.settings.initial_guess = (
            proxqp.InitialGuess.WARM_START_WITH_PREVIOUS_RESULT
        )
        self._big = 1e20
        self._l, self._u = np.zeros(n_in), np.zeros(n_in)
        self._lo, self._hi = np.zeros(n), np.zeros(n)
        self._clip(qp)
        self._qp.init(
            qp.H, qp.g, qp.A_eq, qp.b_eq, qp.A_in, self._l, self._u, self._lo, self._hi
        )
        self._status = proxqp.QPSolverOutput
        self._x = np.zeros(n)

    def _clip(self, qp) -> None:
        big = self._big
        np.clip(qp.l_in, -big, big, out=self._l)
        np.clip(qp.u_in, -big, big, out=self._u)
        np.clip(qp.lo, -big, big, out=self._lo)
        np.clip(qp.hi, -big, big, out=self._hi)

    def update(self, qp) -> None:
        self._clip(qp)
        self._qp.update(
            qp.H, qp.g, qp.A_eq, qp.b_eq, qp.A_in, self._l, self._u, self._lo, self._hi
        )

    def solve(self) -> tuple[int, np.ndarray]:
        self._qp.solve()
        status = self._qp.results.info.status
        if status == self._status.PROXQP_SOLVED:
            self._x[:] = self._qp.results.x
            return 0, self._x
        if status in (
            self._status.PROXQP_PRIMAL_INFEASIBLE,
            self._status.PROXQP_DUAL_INFEASIBLE,
        ):
            return 2, self._x
        return 3, self._x


def standing(robot):
    """The plant, a context at the standing pose (lowest sole on z = 0) and the
    joint indexing."""
    from hrp2_drake.multibody import joint_indexing
    from hrp2_drake.robot.station import standing_positions

    plant = robot.make_plant()
    context = plant.CreateDefaultContext()
    plant.SetPositions(context, standing_positions(robot))
    return plant, context, joint_indexing(plant, robot.joints)


def states(plant, context, indexing, ticks, seed=0):
    """A smooth 1 kHz sequence of [q; v] around the standing pose (the module
    docstring)."""
    rng = np.random.default_rng(seed)
    n = indexing.size
    amplitude = rng.uniform(0.01, 0.04, n)
    omega = 2 * np.pi * rng.uniform(0.5, 2.0, n)
    phase = rng.uniform(0, 2 * np.pi, n)
    x0 = plant.GetPositionsAndVelocities(context)
    nq = plant.num_positions()
    out = np.tile(x0, (ticks, 1))
    t = np.arange(ticks)[:, None] * 0.001
    out[:, indexing.q] += amplitude * np.sin(omega * t + phase)
    out[:, nq + indexing.v] = amplitude * omega * np.cos(omega * t + phase)
    return out


def make_backend(step, solver):
    from hrp2_drake.control.balance import make_qp_backend

    backends = {"proxsuite": ProxsuiteQp, "osqp_pip": PipOsqp, "quadprog": Quadprog}
    if solver in backends:
        return backends[solver](step.qp)
    return make_qp_backend(step.qp, solver)


def bench(robot, solvers, ticks):
    """Per tick: the QP assembled once (Drake's terms and `balance_assemble`), then
    every solver's update and solve on the same numbers (each its own warm start),
    τ from the first solver's solution (`balance_outputs`), and one
    CalcInverseDynamics: every time of a tick under the same load."""
    from pydrake.multibody.tree import MultibodyForces

    from hrp2_drake.assembly.balance import sole_poses
    from hrp2_drake.control.balance import BalanceConfig, WholeBodyBalanceControllerStep
    from hrp2_drake.estimation.base_kinematics import FloatingBaseFromSolesStep

    plant, context, indexing = standing(robot)
    com = plant.CalcCenterOfMassPositionInWorld(context)
    com_ref = np.r_[com + [0.0, 0.02, 0.0], np.zeros(6)]
    q_ref = robot.home_positions()
    step = WholeBodyBalanceControllerStep(
        plant,
        BalanceConfig(joints=robot.joints).for_robot(robot.balance, robot.source_file),
        robot.contacts,
    )
    step.warm_up()
    base = FloatingBaseFromSolesStep(
        plant, robot.joints, sole_poses(robot, plant.GetPositions(context))
    )
    base.warm_up()
    nq = plant.num_positions()
    backends = [make_backend(step, solver) for solver in solvers]
    rnea_plant = robot.make_plant()
    rnea_context = rnea_plant.CreateDefaultContext()
    forces = MultibodyForces(rnea_plant)
    vdot = np.full(rnea_plant.num_velocities(), 0.1)
    sequence = states(plant, context, indexing, ticks)
    solve_ns = np.zeros((len(solvers), ticks), np.int64)
    rest_ns = np.zeros(ticks, np.int64)
    base_ns = np.zeros(ticks, np.int64)
    rnea_ns = np.zeros(ticks, np.int64)
    faults = np.zeros(len(solvers), int)
    tau_gap = np.zeros(len(solvers))
    gc.collect()
    gc.freeze()
    gc.disable()
    try:
        for k in range(ticks):
            start = time.perf_counter_ns()
            step._x[:] = sequence[k]
            step._assemble(q_ref, com_ref)
            assembled = time.perf_counter_ns()
            solutions = []
            for b, backend in enumerate(backends):
                t0 = time.perf_counter_ns()
                backend.update(step.qp)
                fault, solution = backend.solve()
                solve_ns[b, k] = time.perf_counter_ns() - t0
                faults[b] += fault != 0
                solutions.append(solution.copy())
            t0 = time.perf_counter_ns()
            step._accept(solutions[0])
            rest_ns[k] = assembled - start + time.perf_counter_ns() - t0
            tau = step.tau_desired.copy()
            for b, solution in enumerate(solutions):
                step._accept(solution)
                tau_gap[b] = max(tau_gap[b], np.abs(step.tau_desired - tau).max())
            q, v = sequence[k, indexing.q], sequence[k, nq + indexing.v]
            t0 = time.perf_counter_ns()
            base.step(k * 0.001, q, v)
            base_ns[k] = time.perf_counter_ns() - t0
            rnea_plant.SetPositionsAndVelocities(rnea_context, sequence[k])
            r0 = time.perf_counter_ns()
            rnea_plant.CalcForceElementsContribution(rnea_context, forces)
            rnea_plant.CalcInverseDynamics(rnea_context, vdot, forces)
            rnea_ns[k] = time.perf_counter_ns() - r0
    finally:
        gc.enable()
        gc.unfreeze()
    return _bench_rows(solvers, solve_ns, rest_ns, base_ns, rnea_ns, faults, tau_gap)


def _bench_rows(solvers, solve_ns, rest_ns, base_ns, rnea_ns, faults, tau_gap):
    """`bench`'s times (ns, a column per tick; the solves a row per solver) as
    (a row per solver, the rest of the step, the base, CalcInverseDynamics): `stats`
    in CalcInverseDynamics' p50, the first ticks left out."""
    skip = min(50, rnea_ns.size // 10)  # the first solves (cold caches, warm start)
    rnea = rnea_ns[skip:] * 1e-3
    rest = rest_ns[skip:] * 1e-3
    unit = float(np.median(rnea))
    rows = []
    for b, solver in enumerate(solvers):
        solve = solve_ns[b, skip:] * 1e-3
        rows.append(
            {
                "solver": solver,
                "solve": stats(solve, unit),
                "step": stats(solve + rest, unit),
                "faults": int(faults[b]),
                "tau_gap": float(tau_gap[b]),
            }
        )
    return (
        rows,
        stats(rest, unit),
        stats(base_ns[skip:] * 1e-3, unit),
        stats(rnea, unit),
    )


def stats(values: np.ndarray, unit: float) -> dict[str, float]:
    """p50 and p99 of times (µs), in µs and in `unit` (µs: CalcInverseDynamics'
    p50 in the same run)."""
    p50, p99 = float(np.median(values)), float(np.percentile(values, 99))
    return {"p50_us": p50, "p99_us": p99, "p50": p50 / unit, "p99": p99 / unit}


class TimedBackend:
    """A step's QP backend, timed in place: `last_ns` is its last `update` +
    `solve` (ns; the solve as `bench` times it), 0 when a tick solved nothing."""

    def __init__(self, backend):
        self.name = backend.name
        self._backend = backend
        self._start = 0
        self.last_ns = 0

    def update(self, qp) -> None:
        self._start = time.perf_counter_ns()
        self._backend.update(qp)

    def solve(self):
        result = self._backend.solve()
        self.last_ns = time.perf_counter_ns() - self._start
        return result


class TimedCall:
    """A function timed in place: `last_ns` is its last call's time (ns)."""

    def __init__(self, function):
        self._function = function
        self.last_ns = 0

    def __call__(self, *args):
        start = time.perf_counter_ns()
        result = self._function(*args)
        self.last_ns = time.perf_counter_ns() - start
        return result


#: The closed loop's torque control starts here (s; the default start_time).
CLOSED_LOOP_START = 0.5


def balance_controller(solver: str, duration: float, robot: str = "hrp2"):
    """The robot `robot` (a description's name or file) standing
    (`StationConfig(robot, scenario="standing")`), the default balance
    control of both legs (`BalanceControlConfig`'s defaults, torque control from
    0.5 s, supervised) with
    the QP solved by `solver`, as one fused controller; its joint reference (the
    standing pose held) and its CoM reference per tick (the authors' sinusoid,
    `sinusoid_com`, from 0.5 s), and the station's config."""
    from hrp2_drake.assembly.balance import (
        BalanceControlConfig,
        balance_chain_parts,
        resolved,
    )
    from hrp2_drake.assembly.builders import JointReference
    from hrp2_drake.control.balance import BalanceConfig
    from hrp2_drake.control.balance_reference import (
        StandingIk,
        leg_joints,
        sinusoid_com,
    )
    from hrp2_drake.control.fused import FusedController
    from hrp2_drake.robot.ground_truth import true_motor_model
    from hrp2_drake.robot.station import StationConfig, standing_positions

    station = StationConfig(robot=robot, scenario="standing")
    station.validate()
    robot = station.description()
    period = station.sensors_config().period
    standing = standing_positions(robot)
    plant = robot.make_plant()
    soles = list(robot.contacts.soles)
    ik = StandingIk(plant, robot.joints, soles, standing)
    reference = JointReference.hold(ik.joint_angles(standing), duration + 1.0)
    t = np.arange(int(round(duration / period)) + 1) * period
    com = sinusoid_com(ik.com(standing), np.maximum(t - CLOSED_LOOP_START, 0.0))
    com[t < CLOSED_LOOP_START, 3:] = 0.0
    config = resolved(robot, BalanceControlConfig(balance=BalanceConfig(solver=solver)))
    motor_model = true_motor_model(robot, leg_joints(plant, robot.joints, soles))
    parts = balance_chain_parts(
        robot, reference, standing, motor_model, config, period=period
    )
    return FusedController(parts), reference, com, station


def bench_closed_loop(solver: str, duration: float = 2.0, robot: str = "hrp2") -> dict:
    """The fused balance controller on the standing `robot` in closed loop
    (`balance_controller`, the station simulated in the same process:
    `run_in_process`), its QP solved by `solver`. Per tick, timed: the tick
    (`tick` + `command`, as bench_fused times it) and, inside it, the QP's update
    and solve (`TimedBackend`), the QP's step and the base's (`TimedCall`); then one
    CalcInverseDynamics (gravity included) of the full floating robot (HRP-2: 36
    velocities) at the base's estimated state, the unit of the ratios. The ticks
    in torque control (the supervisor's ramp done) count; the garbage collector
    frozen and disabled, compiling frozen after `warm_up`, as in the control loop.
    Returns the `stats` of the tick, the solve, the QP's step, the base, the rest
    of the tick and the unit, the ticks counted and the QP faults."""
    from pydrake.multibody.tree import MultibodyForces

    from hrp2_drake import kernels
    from hrp2_drake.hardware.in_process import run_in_process
    from hrp2_drake.hardware.real_time import garbage_collector_frozen
    from hrp2_drake.robot.station import make_station

    controller, reference, com, station = balance_controller(solver, duration, robot)
    backend = controller.balance._backend = TimedBackend(controller.balance._backend)
    base = controller.base.step = TimedCall(controller.base.step)
    qp_step = controller.balance.step = TimedCall(controller.balance.step)
    warm_up = controller.warm_up()
    make_station(station)  # its servo's and sensors' kernels too, before freezing
    plant = station.description().make_plant()
    context = plant.CreateDefaultContext()
    forces = MultibodyForces(plant)
    vdot = np.full(plant.num_velocities(), 0.1)
    ticks = len(com) - 1
    tick_ns, solve_ns, base_ns, qp_ns, rnea_ns = np.zeros((5, ticks), np.int64)
    active = np.zeros(ticks, bool)
    counter = {"k": 0}
    base_state = controller.signals()["base_state"]

    def timed(step):
        k = counter["k"]
        controller.com_ref[:] = com[k]
        backend.last_ns = 0
        start = time.perf_counter_ns()
        step()
        middle = time.perf_counter_ns()
        plant.SetPositionsAndVelocities(context, base_state)
        r0 = time.perf_counter_ns()
        plant.CalcForceElementsContribution(context, forces)
        plant.CalcInverseDynamics(context, vdot, forces)
        rnea_ns[k] = time.perf_counter_ns() - r0
        tick_ns[k], solve_ns[k] = middle - start, backend.last_ns
        base_ns[k], qp_ns[k] = base.last_ns, qp_step.last_ns
        active[k] = controller.torque_active() >= 1.0
        counter["k"] = k + 1

    with garbage_collector_frozen(), kernels.compile_disabled():
        run_in_process(station, controller, reference, ticks, on_tick=timed)
    unit = float(np.median(rnea_ns[active])) * 1e-3
    return {
        "solver": solver,
        "robot": station.description().name,
        "tick": stats(tick_ns[active] * 1e-3, unit),
        "solve": stats(solve_ns[active] * 1e-3, unit),
        "base": stats(base_ns[active] * 1e-3, unit),
        "qp_step": stats(qp_ns[active] * 1e-3, unit),
        "rest": stats((tick_ns - base_ns - qp_ns)[active] * 1e-3, unit),
        "rnea": stats(rnea_ns[active] * 1e-3, unit),
        "ticks": int(active.sum()),
        "qp_faults": int(controller.signals()["balance_fault_count"][0]),
        "warm_up_s": warm_up,
    }


#: A real robot's control period (s): HRP-2's 1 kHz.
PERIOD_BUDGET_US = 1000.0


def closed_loop_rows(duration: float = 2.0, robot: str = "hrp2") -> list[dict]:
    """`bench_closed_loop` on `robot` for daqp (the default) and pydrake's OSQP, as
    rows for scripts/bench.py (a line saying a solver is skipped if it is not
    installed); printed as they come, with what they mean for a 1 kHz robot."""
    rows = []

    def say(row):
        cells = [
            f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}"
            for k, v in row.items()
        ]
        print("  " + ", ".join(cells), file=sys.stderr)
        rows.append(row)

    for solver in ("daqp", "osqp"):
        if not available(solver):
            say({"name": f"{solver}: skipped (not installed: pip install {solver})"})
            continue
        result = bench_closed_loop(solver, duration, robot)
        unit = result["rnea"]
        say(
            {
                "name": f"CalcInverseDynamics, full {result['robot']} ({solver} run)",
                "p50_us": unit["p50_us"],
                "p99_us": unit["p99_us"],
            }
        )
        for what, key in (
            ("QP solve (update + solve)", "solve"),
            ("QP step (Drake's terms, assembly, solve, τ)", "qp_step"),
            ("base from the soles (its step)", "base"),
            ("the rest of the tick (filters, estimator, Δq, supervisor)", "rest"),
            ("fused balance tick (tick + command)", "tick"),
        ):
            timed = result[key]
            say({"name": f"{what}, {solver}", **timed, "ticks": result["ticks"]})
        say(
            {"name": meaning(solver, result["tick"])}
            | {"qp_faults": result["qp_faults"], "warm_up_s": result["warm_up_s"]}
        )
    return rows


def meaning(solver: str, tick: dict) -> str:
    """What a tick's p50/p99 (µs) mean for a robot at 1 kHz (1 ms a tick, which
    must also hold the link's I/O: receive, decode, publish)."""
    p50, p99 = tick["p50_us"], tick["p99_us"]
    budget = PERIOD_BUDGET_US
    if p99 <= budget:
        verdict = f"fits, {budget - p99:.0f} µs left at p99 for the link's I/O"
    elif p50 <= budget:
        verdict = "overruns on more than 1 % of the ticks"
    else:
        verdict = "overruns on most ticks"
    return (
        f"{solver} at 1 kHz on a real robot (1 ms a tick): p50 "
        f"{100 * p50 / budget:.0f} %, p99 {100 * p99 / budget:.0f} % of the period: "
        f"{verdict}; the rate its p99 allows, the I/O aside: {1e6 / p99:.0f} Hz"
    )


def available(solver):
    module = {
        "daqp": "daqp",
        "proxsuite": "proxsuite",
        "osqp_pip": "osqp",
        "quadprog": "quadprog",
    }.get(solver)
    if module is None:
        return True
    try:
        __import__(module)
    except ImportError:
        return False
    return True


def main() -> int:
    from hrp2_drake.description import load_robot_description

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--robot",
        default="hrp2",
        help="a robot description with soles (a robot.yaml or a name in models/; "
        "default: hrp2)",
    )
    parser.add_argument("--ticks", type=int, default=2000)
    parser.add_argument("--solvers", default=",".join(DRAKE_AND_OPTIONAL + BENCH_ONLY))
    parser.add_argument(
        "--closed-loop", action="store_true", help="the QP in the fused controller"
    )
    parser.add_argument(
        "--duration", type=float, default=2.0, help="closed loop: simulated s"
    )
    args = parser.parse_args()
    try:
        robot = load_robot_description(args.robot)
    except (ValueError, OSError) as error:
        parser.error(f"--robot {args.robot}: {error}")
    if robot.base == "fixed" or not robot.contacts.soles:
        parser.error(f"--robot {args.robot}: no soles to stand on (contacts.soles)")
    if args.closed_loop:
        closed_loop_rows(args.duration, args.robot)
        return 0
    solvers = [s for s in args.solvers.split(",") if available(s)]
    rows, rest, base, rnea = bench(robot, solvers, args.ticks)
    print(
        f"{robot.name} double support, {args.ticks} ticks; CalcInverseDynamics (full "
        f"{robot.name}, {robot.make_plant().num_velocities()} velocities, gravity) p50 "
        f"{rnea['p50_us']:.1f} µs, p99 {rnea['p99_us']:.1f} µs: the unit (ID)"
    )
    print(
        f"the step without the solve (Drake's terms, the kernels): p50 "
        f"{rest['p50_us']:.0f} µs ({rest['p50']:.1f} ID), p99 "
        f"{rest['p99_us']:.0f} µs ({rest['p99']:.1f} ID)"
    )
    print(
        f"its input, the base from the soles (FloatingBaseFromSolesStep.step): p50 "
        f"{base['p50_us']:.0f} µs ({base['p50']:.1f} ID), p99 "
        f"{base['p99_us']:.0f} µs ({base['p99']:.1f} ID)\n"
    )
    print(
        "| solver | solve p50 / p99 (µs) | solve p50 / p99 (ID) "
        "| step p50 / p99 (ID) | faults | max abs τ gap to the first (N·m) |"
    )
    print("| --- | --- | --- | --- | --- | --- |")
    for row in rows:
        solve, whole = row["solve"], row["step"]
        print(
            f"| {row['solver']} | {solve['p50_us']:.0f} / {solve['p99_us']:.0f} "
            f"| {solve['p50']:.1f} / {solve['p99']:.1f} "
            f"| {whole['p50']:.1f} / {whole['p99']:.1f} "
            f"| {row['faults']} | {row['tau_gap']:.1e} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
