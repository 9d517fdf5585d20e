#!/usr/bin/env python3
"""The whole-body balance QP's solve on HRP-2, per solver, against Drake's own
`CalcInverseDynamics` on the full HRP-2 in the same run (issue 29: choose the solver
by measurement).

HRP-2 in double support (60 variables, 18 equalities, 62 inequality rows and 38
bounds: `BalanceStep.sizes`), at states of a smooth 1 kHz sequence around the
standing (half-sitting) pose: every joint oscillating by a few 0.01 rad at 0.5-2 Hz
with its velocity, the CoM's reference 2 cm to the left. One `BalanceStep` built
once; per tick, timed: the rest of the step (Drake's terms and the kernels that
assemble the QP and write τ), each solver's solve on the same QP (the coefficients'
update and the solve: `QpBackend.update` + `solve`; each solver keeps its own warm
start), and one `CalcInverseDynamics` (gravity included) of the full floating HRP-2
(36 velocities) at the same state, the unit of the ratios: every time of a tick is
taken under the same load. A solver's step is the rest plus its solve. Also per
tick, the QP's input: the base's state from the soles' kinematics
(`BaseFromSolesStep.step`, the soles where they stood) from the same joint angles
and velocities. The garbage collector is frozen and disabled, as in the control
loop.

Solvers: pydrake's OsqpSolver and ClarabelSolver (MathematicalProgram built once,
UpdateCoefficients on the bindings, the last solution as initial guess), the pip
package daqp (the optional `qp` extra), and, only here, the pip packages proxsuite
(dense ProxQP, warm-started), osqp (its own workspace, warm-started) and quadprog
(cold, dense). A solver not installed is skipped.

    python scripts/bench_balance.py [--ticks 2000] [--solvers osqp,daqp]
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
    from hrp2_drake.control.balance import BalanceConfig, BalanceStep
    from hrp2_drake.estimation.base_kinematics import BaseFromSolesStep

    plant, context, indexing = standing(robot)
    com = plant.CalcCenterOfMassPositionInWorld(context)
    com_ref = np.r_[com + [0.0, 0.02, 0.0], np.zeros(6)]
    q_ref = robot.home_positions()
    step = BalanceStep(plant, BalanceConfig(joints=robot.joints), robot.contacts)
    step.warm_up()
    base = BaseFromSolesStep(
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
    skip = min(50, ticks // 10)  # the first solves (cold caches, first warm start)
    rnea = rnea_ns[skip:] * 1e-3
    rest = rest_ns[skip:] * 1e-3
    unit = float(np.median(rnea))

    def stats(values):
        p50, p99 = float(np.median(values)), float(np.percentile(values, 99))
        return {"p50_us": p50, "p99_us": p99, "p50": p50 / unit, "p99": p99 / unit}

    rows = []
    for b, solver in enumerate(solvers):
        solve = solve_ns[b, skip:] * 1e-3
        rows.append(
            {
                "solver": solver,
                "solve": stats(solve),
                "step": stats(solve + rest),
                "faults": int(faults[b]),
                "tau_gap": float(tau_gap[b]),
            }
        )
    return rows, stats(rest), stats(base_ns[skip:] * 1e-3), stats(rnea)


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
    parser.add_argument("--ticks", type=int, default=2000)
    parser.add_argument("--solvers", default=",".join(DRAKE_AND_OPTIONAL + BENCH_ONLY))
    args = parser.parse_args()
    robot = load_robot_description("hrp2")
    solvers = [s for s in args.solvers.split(",") if available(s)]
    rows, rest, base, rnea = bench(robot, solvers, args.ticks)
    print(
        f"HRP-2 double support, {args.ticks} ticks; CalcInverseDynamics (full HRP-2, "
        f"36 velocities, gravity) p50 {rnea['p50_us']:.1f} µs, p99 "
        f"{rnea['p99_us']:.1f} µs: the unit (ID)"
    )
    print(
        f"the step without the solve (Drake's terms, the kernels): p50 "
        f"{rest['p50_us']:.0f} µs ({rest['p50']:.1f} ID), p99 "
        f"{rest['p99_us']:.0f} µs ({rest['p99']:.1f} ID)"
    )
    print(
        f"its input, the base from the soles (BaseFromSolesStep.step): p50 "
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
