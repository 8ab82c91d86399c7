"""The two inner NLPs of MACSoc, built once per problem per worker process, and the kernel
that runs one of them.

* **Pascoletti–Serafini local search** (eq. 11–13, individualistic action): variables
  (z, α), min α + 1e-3 Σ_i ϑ_i s.t. λ_i ϑ_i(z) ≤ α, ϑ_i = (J_i(z) − z̃_i)/(z*_i − z̃_i),
  the DFET constraints and bounds. Parameters: λ (m), z̃ (m), z* (m).
* **Constraint restoration** (eq. 14 inner level, social action): min 1 s.t. the DFET
  constraints and bounds, from a candidate.
* **ε-constraint refinement** (the final refinement of the archive, our addition): variables
  z, min J_k(z)/s_k s.t. (J_i(z) − ε_i)/s_i ≤ 0 for i ≠ k, the DFET constraints and bounds,
  with ε = J of the member it refines (started from the member's own NLP vector or from a
  neighbour's) and k = :data:`REFINED_OBJECTIVE`. Parameters: ε (m), s (m) the archive's span.
* **Pareto stationarity** of a refined member (kind "stationarity", no NLP): its first-order
  residual (:meth:`InnerSolvers.stationarity`).

Counting evaluations: a local search counts one objective evaluation per evaluation of its
constraint function (each one evaluates J(z)) plus one for the start point, summed over its
seam hops (below); a restoration counts one (the objectives of the point it returns); a
refinement counts like a local search; a stationarity measure counts none.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from functools import cached_property, lru_cache

import casadi as ca
import numpy as np
from scipy.optimize import nnls

from ocpar.macs.archive import TIE_TOL
from ocpar.macs.objectives import objective_functions
from ocpar.macs.problem import MacsProblem
from ocpar.ocp import DfetTranscription, dfet_problem
from ocpar.ocp.batch import BufferedFunction
from ocpar.ocp.solver_options import SolverOptions, ipopt

#: A result counts as feasible when IPOPT succeeds and max |g| ≤ this (the paper's tol_con).
FEASIBILITY_TOL = 1e-6
#: ... and when its objectives, recomputed by integrating its control law accurately, agree
#: with the transcription's to this (relative to 1 + |J|): otherwise the optimiser has
#: exploited the transcription's error (seen on orbit raising, 30 elements of order 1, near
#: t_f = 80) and the point is rejected like an infeasible one.
CONSISTENCY_TOL = 1e-2
#: Relative tolerance of the integrations of a local search: the state nodes of a start
#: point given as a decision vector, and the re-simulation of the consistency check (far
#: below :data:`CONSISTENCY_TOL`; at this tolerance the compiled RK4 sweep of the DFET
#: usually suffices, see :meth:`~ocpar.ocp.dfet.DfetTranscription.rk4_sweep`).
INTEGRATION_RTOL = 1e-5
#: IPOPT iteration limit of one local search (the paper gave fmincon 100 evaluations).
MAX_ITER = 100
KINDS = ("scalarised", "restore", "refine", "stationarity")
#: The objective a refinement minimises (the last: t_f is the first of every example, so a
#: member keeps its final time and gets the least J_m for it); the others are bounded.
REFINED_OBJECTIVE = -1
#: A member whose Pareto-stationarity residual is at most this counts as converged.
STATIONARITY_TOL = 1e-6
#: Weight of Σ_i ϑ_i added to α (augmented Pascoletti–Serafini): without it a search that
#: reaches a bound of one objective (t_f = 20 in orbit raising) stops at a weakly Pareto
#: optimal point instead of also improving the other objective.
AUGMENTATION = 1e-3
#: A control node of a periodic control within this (rad) of a bound is on the seam.
SEAM_TOL = 1e-3
#: At most this many seam hops (re-searches) per scalarised search.
MAX_SEAM_HOPS = 3
#: IPOPT's initial barrier parameter for the scalarised search (default 0.1): the start is
#: a feasible or nearly feasible trajectory, and a smaller barrier keeps IPOPT from first
#: pushing it into the interior of the control box (on orbit raising ~35 instead of ~57
#: evaluations per search for the same results).
SEARCH_MU_INIT = 1e-3
#: How a restoration (min 0 s.t. the DFET constraints) stops: ``centred``, IPOPT to tol 1e-8,
#: which goes on after the point is feasible until the complementarity is 1e-8 too, moving it
#: along the central path between its bounds; or ``feasible``, at the first point feasible to
#: 1e-8, with the adaptive barrier parameter (:data:`FEASIBLE_RESTORATION_OPTIONS`). A problem
#: with path constraints always restores to ``feasible``: a one-sided row (v ≤ v_max) leaves
#: the central path of min 0 without a centre, and IPOPT drags the point along it (on the
#: tutorial's drag cart an inactive v ≤ 10 lowered the hypervolume from 0.96 to 0.73).
RESTORATIONS = ("centred", "feasible")
#: IPOPT options of a ``feasible`` restoration. On Goddard's restorations: 4.2 instead of
#: 12.3 iterations, ~0.5x the CPU time; the point stays nearer the candidate.
FEASIBLE_RESTORATION_OPTIONS = {"constr_viol_tol": 1e-8, "dual_inf_tol": 1.0,
                                "compl_inf_tol": 1.0, "mu_strategy": "adaptive"}


@dataclass(frozen=True)
class SearchTask:
    """One inner solve: ``kind`` "scalarised" (Pascoletti–Serafini, needs ``weights`` λ,
    ``utopia`` z̃), "restore", "refine" (ε-constraint, needs ``span`` s (m,), the scale of
    each objective, and takes ``epsilon`` (m,), the objectives of the member it refines, which
    its point must dominate or equal; None: those of its start) or "stationarity" (of the
    point ``z0``, with ``span``); the start is ``z0`` (full NLP vector) or, if None, the
    decision vector ``p0`` (controls and t_f) from which the states are integrated. The
    result is clipped to the bounds (IPOPT relaxes them by ~1e-8). ``solver_options``: IPOPT's
    own options over :func:`search_settings`' defaults (:mod:`ocpar.ocp.solver_options`)."""

    problem: MacsProblem
    kind: str
    z0: np.ndarray | None = None
    p0: np.ndarray | None = None
    weights: np.ndarray | None = None
    utopia: np.ndarray | None = None
    restoration: str = "centred"
    span: np.ndarray | None = None
    epsilon: np.ndarray | None = None
    solver_options: SolverOptions = ()


@dataclass
class SearchResult:
    """``z`` the NLP vector reached, ``objectives`` J(z) (m,), ``feasible``, ``evaluations``
    counted as in the module docstring, IPOPT ``status`` and ``iterations``. A refinement
    also returns whether its solve was kept (``refined``: feasible and dominating or equal to
    its ε; else ``z`` is the start); a stationarity task the Pareto-stationarity residual
    ``stationarity`` of its point and the trade-off weights ``tradeoff`` (m,)
    (:meth:`InnerSolvers.stationarity`)."""

    z: np.ndarray
    objectives: np.ndarray
    feasible: bool
    evaluations: int
    status: str
    iterations: int
    solve_time_s: float
    refined: bool = False
    stationarity: float | None = None
    tradeoff: np.ndarray | None = None


def search_settings(options: SolverOptions = ()) -> dict[str, dict]:
    """The ``nlpsol`` options of the inner NLPs by kind (``scalarised``, ``restore``,
    ``restore_feasible``, ``refine``): IPOPT to 1e-8 in :data:`MAX_ITER` iterations (the
    searches from :data:`SEARCH_MU_INIT`; a ``feasible`` restoration with
    :data:`FEASIBLE_RESTORATION_OPTIONS`), the user's ``ipopt.*`` ``options`` over them."""
    return {"scalarised": ipopt(options, 1e-8, MAX_ITER, mu_init=SEARCH_MU_INIT),
            "restore": ipopt(options, 1e-8, MAX_ITER),
            "restore_feasible": ipopt(options, 1.0, MAX_ITER, **FEASIBLE_RESTORATION_OPTIONS),
            "refine": ipopt(options, 1e-8, MAX_ITER, mu_init=SEARCH_MU_INIT)}


class InnerSolvers:
    """The DFET transcription of a problem with its two solvers and J(z) as a function;
    ``options`` the user's IPOPT options (:func:`search_settings`)."""

    def __init__(self, problem: MacsProblem, options: SolverOptions = ()) -> None:
        self.problem = problem
        self.settings = search_settings(options)
        self.dfet: DfetTranscription = dfet_problem(problem.shape)
        self.functions = objective_functions(problem)
        z = self.dfet.z
        objectives = self.functions.symbolic(z)
        m = problem.n_objectives
        # J(z) and g(z) through numpy buffers: ~1 µs of conversions instead of ~50-100 µs
        self._objectives = BufferedFunction(ca.Function("J", [z], [objectives]))
        path = self.dfet.path_rows(problem.path_constraints)
        g = ca.vertcat(self.dfet.constraints, path.expr)
        self._residual = BufferedFunction(ca.Function("g", [z], [g]))
        self.ng = g.numel()
        #: Bounds of g: the DFET equations = 0, then the path rows' (none without any).
        self.lbg = np.concatenate([np.zeros(self.dfet.ng), path.lower])
        self.ubg = np.concatenate([np.zeros(self.dfet.ng), path.upper])
        self._g = g

        alpha = ca.SX.sym("alpha")
        lam, utopia, start = ca.SX.sym("lam", m), ca.SX.sym("zt", m), ca.SX.sym("zs", m)
        theta = (objectives - utopia) / (start - utopia)
        scalarised = {"x": ca.vertcat(z, alpha), "p": ca.vertcat(lam, utopia, start),
                      "f": alpha + AUGMENTATION * ca.sum1(theta),
                      "g": ca.vertcat(g, lam * theta - alpha)}
        eps, span = ca.SX.sym("eps", m), ca.SX.sym("span", m)
        epsilon = {"x": z, "p": ca.vertcat(eps, span),
                   "f": objectives[REFINED_OBJECTIVE] / span[REFINED_OBJECTIVE],
                   "g": ca.vertcat(g, (objectives - eps) / span)}
        self.epsilon = ca.nlpsol("eps", "ipopt", epsilon, self.settings["refine"])
        # ∂J/∂z (m, nz) and ∂g/∂z (ng, nz), dense, for the stationarity measure
        self._jacobians = BufferedFunction(ca.Function(
            "dJg", [z], [ca.densify(ca.jacobian(objectives, z)), ca.densify(ca.jacobian(g, z))]))
        self.scalarised = ca.nlpsol("ps", "ipopt", scalarised, self.settings["scalarised"])
        self.restore = ca.nlpsol("restore", "ipopt", {"x": z, "f": 0, "g": g},
                                 self.settings["restore"])

    def violation(self, z: np.ndarray) -> float:
        """max over g's rows of how far z breaks its bounds (0 when feasible)."""
        g = self._residual(z)[0]
        return float(np.max(np.maximum(self.lbg - g, g - self.ubg), initial=0.0))

    @cached_property
    def restore_feasible(self) -> ca.Function:
        """The restoration that stops at the first feasible point, built on first use."""
        return ca.nlpsol("restore_feasible", "ipopt", {"x": self.dfet.z, "f": 0,
                                                       "g": self._g},
                         self.settings["restore_feasible"])

    def consistent(self, z: np.ndarray, objectives: np.ndarray) -> bool:
        """The transcription's objectives agree with an accurate re-simulation of z's
        control law (:data:`CONSISTENCY_TOL`)."""
        try:
            simulated = self.functions.resimulated(z, rtol=INTEGRATION_RTOL)
        except RuntimeError:
            return False
        return bool(np.all(np.abs(simulated - objectives) <= CONSISTENCY_TOL
                           * (1 + np.abs(objectives))))

    def start_point(self, task: SearchTask) -> np.ndarray:
        if task.z0 is not None:
            return np.clip(task.z0, self.dfet.lbz, self.dfet.ubz)
        return self.dfet.guess_from_decision(task.p0, INTEGRATION_RTOL)

    def run(self, task: SearchTask) -> SearchResult:
        """One inner solve. A scalarised search or refinement of a problem with
        ``periodic_controls`` that ends with nodes of a periodic control on a bound moves
        those nodes to the opposite bound (the same angle) and solves again, up to
        :data:`MAX_SEAM_HOPS` times: the bound is where the angle wraps, not a limit, and a
        node resting on it is a spurious local optimum. Evaluations and time of every solve
        are summed. A stationarity task only measures its point."""
        t0 = time.perf_counter()
        z0 = self.start_point(task)
        if task.kind == "stationarity":
            residual, weights = self.stationarity(z0, task.span)
            return SearchResult(z=z0, objectives=self.objectives(z0), feasible=True,
                                evaluations=0, status="measured", iterations=0,
                                solve_time_s=time.perf_counter() - t0,
                                stationarity=residual, tradeoff=weights)
        if task.kind == "refine":
            # every re-solve must dominate or equal the member refined
            start = self.objectives(z0) if task.epsilon is None else np.asarray(task.epsilon)

            def solve(z: np.ndarray) -> SearchResult:
                return self._refine(task, z, start)

            def done(result: SearchResult) -> bool:
                return result.refined
        else:
            def solve(z: np.ndarray) -> SearchResult:
                return self._solve(task, z)

            def done(result: SearchResult) -> bool:
                return result.feasible
        result = solve(z0)
        evaluations = result.evaluations
        hop_seams = task.kind != "restore" and any(self.problem.periodic_controls)
        for _ in range(MAX_SEAM_HOPS if hop_seams else 0):
            hopped = self._hop_seams(result.z) if done(result) else None
            if hopped is None:
                break
            retry = solve(hopped)
            evaluations += retry.evaluations
            if not done(retry):
                break
            result = retry
        result.evaluations = evaluations
        result.solve_time_s = time.perf_counter() - t0
        return result

    @cached_property
    def _periodic(self) -> np.ndarray:
        """Which entries of z (nz,) are nodes of a periodic control."""
        controls = slice(self.dfet.decision_slice.start, self.dfet.nz - 1)
        mask = np.zeros(self.dfet.nz, dtype=bool)
        # nodes component-fastest
        mask[controls] = np.resize(self.problem.periodic_controls, controls.stop - controls.start)
        return mask

    def _hop_seams(self, z: np.ndarray) -> np.ndarray | None:
        """z with every node of a periodic control within :data:`SEAM_TOL` of a bound moved
        to the opposite bound, or None if no such node is on a bound."""
        controls = slice(self.dfet.decision_slice.start, self.dfet.nz - 1)
        u, lower, upper = z[controls], self.dfet.lbz[controls], self.dfet.ubz[controls]
        periodic = self._periodic[controls]
        at_lower = periodic & (u <= lower + SEAM_TOL)
        at_upper = periodic & (u >= upper - SEAM_TOL)
        if not np.any(at_lower | at_upper):
            return None
        hopped = z.copy()
        hopped[controls] = np.where(at_lower, upper, np.where(at_upper, lower, u))
        return hopped

    def _refine(self, task: SearchTask, z0: np.ndarray, start: np.ndarray) -> SearchResult:
        """The ε-constraint NLP from z0 with ε = ``start``, the member's objectives (m,); its
        point is kept if it is feasible and dominates or equals them (ties to
        :data:`~ocpar.macs.archive.TIE_TOL`), else z0 is returned (``refined`` False; from a
        neighbour's start, a point that need not dominate the member)."""
        free = np.arange(start.size) == start.size + REFINED_OBJECTIVE  # the minimised one
        out = self.epsilon(
            x0=z0, p=np.concatenate([start, task.span]), lbx=self.dfet.lbz, ubx=self.dfet.ubz,
            lbg=np.concatenate([self.lbg, np.full(start.size, -np.inf)]),
            ubg=np.concatenate([self.ubg, np.where(free, np.inf, 0.0)]))
        stats = self.epsilon.stats()
        z = np.clip(np.asarray(out["x"]).ravel(), self.dfet.lbz, self.dfet.ubz)
        objectives = self.objectives(z)
        refined = (bool(stats["success"]) and self.violation(z) <= FEASIBILITY_TOL
                   and bool(np.all(np.isfinite(z)))
                   and bool(np.all(objectives <= start + TIE_TOL * (1 + np.abs(start))))
                   and self.consistent(z, objectives))
        if not refined:
            z, objectives = z0, self.objectives(z0)
        return SearchResult(z=z, objectives=objectives, feasible=True,
                            evaluations=int(stats.get("n_call_nlp_g", 0)) + 1,
                            status=str(stats["return_status"]),
                            iterations=int(stats["iter_count"]), solve_time_s=0.0,
                            refined=refined)

    def stationarity(self, z: np.ndarray, span: np.ndarray) -> tuple[float, np.ndarray]:
        """First-order Pareto stationarity of a feasible z: the KKT residual of
        min Σ_i w_i J_i/s_i at the trade-off weights w ≥ 0 (Σ w = 1) and multipliers that fit
        it best, max(‖Σ_i w_i ∇J_i/s_i + ∇gᵀλ + ν‖∞, max |complementarity|): λ free on the
        DFET equations, each bound of a path row or of z with its KKT sign and its
        complementarity product (multiplier × distance to the bound) in the fit, so no
        activity threshold is needed; a periodic control's bounds are no limits (the seam)
        and get none. Fitted by non-negative least squares (Lawson–Hanson; on orbit raising's
        305 variables ~1 s from a point off the front, 5-16 s by scipy's bvls). Returns
        (residual, w (m,)); the residual is in units of the normalised objectives J_i/s_i (per
        unit of z for the gradient part), 0 at a KKT point."""
        dj, dg = self._jacobians(z)
        nz = z.size
        grads = dj.reshape(nz, -1).T / span[:, None]  # (m, nz) of J_i/s_i
        dg = dg.reshape(nz, -1).T  # (ng, nz)
        m, g = grads.shape[0], self._residual(z)[0]
        equality = self.lbg == self.ubg
        fixed = self.dfet.lbz == self.dfet.ubz
        bounded = ~fixed & ~self._periodic
        # one column per bound: its gradient (a row of ∂g/∂z, or a unit vector), its sign
        # (-1 lower: multiplier ≤ 0; +1 upper: ≥ 0) and the distance to it
        bounds = [(dg[rows], sign, np.abs(distance[rows]))
                  for rows, sign, distance in (
                      (~equality & np.isfinite(self.lbg), -1.0, g - self.lbg),
                      (~equality & np.isfinite(self.ubg), 1.0, self.ubg - g))]
        eye = np.eye(nz)
        bounds += [(eye[cols], sign, np.abs(distance[cols]))
                   for cols, sign, distance in (
                       (bounded & np.isfinite(self.dfet.lbz), -1.0, z - self.dfet.lbz),
                       (bounded & np.isfinite(self.dfet.ubz), 1.0, self.dfet.ubz - z))]
        gradients = np.vstack([grads, dg[equality], eye[fixed]] + [b[0] for b in bounds])
        n_free = int(equality.sum() + fixed.sum())
        lower = np.concatenate([np.zeros(m), np.full(n_free, -np.inf)]
                               + [np.where(b[1] < 0, -np.inf, 0.0) * np.ones(len(b[2]))
                                  for b in bounds])
        upper = np.concatenate([np.full(m + n_free, np.inf)]
                               + [np.where(b[1] < 0, 0.0, np.inf) * np.ones(len(b[2]))
                                  for b in bounds])
        distances = np.concatenate([b[2] for b in bounds])
        n = gradients.shape[0]
        complementarity = np.zeros((distances.size, n))
        complementarity[:, n - distances.size:] = np.diag(distances)
        # Σ w = 1 as a heavily weighted row of the least-squares system
        weight = 1e3 * max(1.0, float(np.max(np.abs(grads))))
        total = np.concatenate([np.full(m, weight), np.zeros(n - m)])
        a = np.vstack([gradients.T, complementarity, total])
        b = np.concatenate([np.zeros(nz + distances.size), [weight]])
        # as non-negative least squares: a free column twice (±), a non-positive one negated
        free = np.isinf(lower) & np.isinf(upper)
        sign = np.where(np.isinf(lower) & ~free, -1.0, 1.0)
        y = nnls(np.hstack([a * sign, -a[:, free]]), b, maxiter=50 * a.shape[1])[0]
        x = sign * y[:a.shape[1]]
        x[free] -= y[a.shape[1]:]
        x /= max(np.sum(x[:m]), 1e-300)
        residual = max(float(np.max(np.abs(gradients.T @ x))),
                       float(np.max(np.abs(complementarity @ x), initial=0.0)))
        return residual, x[:m]

    def objectives(self, z: np.ndarray) -> np.ndarray:
        """J(z) (m,) on the transcription."""
        return self._objectives(z)[0]

    def _solve(self, task: SearchTask, z0: np.ndarray) -> SearchResult:
        if task.kind == "scalarised":
            # keep z* − z̃ positive when the start lies beyond the shifted utopia point
            start = np.maximum(self.objectives(z0),
                               task.utopia + 1e-6 * (1 + np.abs(task.utopia)))
            params = np.concatenate([task.weights, task.utopia, start])
            alpha0 = 1.0
            out = self.scalarised(
                x0=np.append(z0, alpha0), p=params,
                lbx=np.append(self.dfet.lbz, -np.inf), ubx=np.append(self.dfet.ubz, np.inf),
                lbg=np.concatenate([self.lbg, np.full(task.weights.size, -np.inf)]),
                # λ_i = 0 drops objective i (its row would only say α ≥ 0)
                ubg=np.concatenate([self.ubg, np.where(task.weights > 0, 0.0, np.inf)]),
            )
            stats = self.scalarised.stats()
            z = np.clip(np.asarray(out["x"]).ravel()[:-1], self.dfet.lbz, self.dfet.ubz)
            evaluations = int(stats.get("n_call_nlp_g", 0)) + 1
        elif task.kind == "restore":
            if task.restoration not in RESTORATIONS:
                raise ValueError(f"unknown restoration {task.restoration!r}; choose one of "
                                 f"{RESTORATIONS}")
            # with path constraints the central path of min 0 need not end at a centre (a
            # one-sided row v ≤ v_max lets the barrier push v to −∞): restore to feasible
            centred = task.restoration == "centred" and not self.problem.path_constraints
            solver = self.restore if centred else self.restore_feasible
            out = solver(x0=z0, lbx=self.dfet.lbz, ubx=self.dfet.ubz, lbg=self.lbg, ubg=self.ubg)
            stats = solver.stats()
            z = np.clip(np.asarray(out["x"]).ravel(), self.dfet.lbz, self.dfet.ubz)
            evaluations = 1
        else:
            raise ValueError(f"unknown search kind {task.kind!r}; choose one of {KINDS}")
        violation = self.violation(z)
        objectives = self.objectives(z)
        feasible = (bool(stats["success"]) and violation <= FEASIBILITY_TOL
                    and bool(np.all(np.isfinite(z)))
                    and self.consistent(z, objectives))
        return SearchResult(
            z=z,
            objectives=objectives,
            feasible=feasible,
            evaluations=evaluations,
            status=str(stats["return_status"]),
            iterations=int(stats["iter_count"]),
            solve_time_s=0.0,
        )


@lru_cache(maxsize=8)
def inner_solvers(problem: MacsProblem, options: SolverOptions = ()) -> InnerSolvers:
    """This process's inner solvers of ``problem`` with IPOPT's ``options``: built once,
    then reused."""
    return InnerSolvers(problem, options)


def run_search(task: SearchTask) -> SearchResult:
    """Engine kernel: one local search or restoration with this process's cached solvers. A
    failed search is infeasible and the algorithm rejects it (the paper's penalty)."""
    return inner_solvers(task.problem, task.solver_options).run(task)
