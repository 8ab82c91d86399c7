"""DFET optimal control: the weak-form dynamics of :mod:`ocpar.ocp.dfet` with boundary data as
parameters and a cost, as a transcription of the inner-problem contract (:mod:`ocpar.ocp.contract`).

    min_z  Φ(x_f, t_f) + Σ_j Σ_k σ_k g(X_j(τ_k), U_j(τ_k)) Δt/2
    s.t.   the weak-form equations from x_0,   x_f[i] = target_i (i in ``final_components``),
           control and duration bounds, the model's state bounds,

with z = (state nodes, x_f, control nodes, t_f) as in :class:`~ocpar.ocp.dfet.DfetTranscription`,
Φ the optional Mayer term ``terminal_cost``, g the model's running cost (if
``running_cost``) integrated by each element's Gauss–Legendre rule, Δt = t_f/N. Parameters
p = (x_0 (nx), target (len(final_components))).

Path constraints (optional, ``DfetOcpShape.path_constraints``, :mod:`ocpar.ocp.constraints`):
functions of ``x`` and ``u``, imposed at each element's quadrature points (the points where
the weak form and the cost evaluate the dynamics and g), where X_j and U_j are the
element's polynomials. Between those points the polynomials are not constrained: the
guarantee is that of a collocation method, O(Δt^{order}) violations in between.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property

import casadi as ca
import numpy as np

from ocpar.models.ode import OdeModel
from ocpar.ocp.constraints import (
    CompiledConstraint,
    PathConstraint,
    compile_constraints,
)
from ocpar.ocp.contract import InnerSolution, call_nlpsol, check_params, transcription
from ocpar.ocp.dfet import DfetShape, DfetTranscription
from ocpar.ocp.solver_options import SolverOptions, ipopt, solver_options


@dataclass(frozen=True)
class DfetOcpShape:
    """Everything that fixes the structure of a DFET optimal control NLP (the solver-cache
    key). ``elements``, ``order``, ``control_order``, ``control_bounds`` and
    ``duration_bounds`` (lo, hi) on t_f (equal bounds: fixed horizon) as in
    :class:`~ocpar.ocp.dfet.DfetShape`; ``final_components`` the state indices fixed at t_f
    (their values are parameters); ``terminal_cost`` an optional Mayer term Φ(x_f, t_f) of
    CasADi symbols (a module-level function, so that the shape pickles); ``running_cost``
    whether the model's g(x, u) is integrated; ``tol``/``max_iter`` IPOPT's settings;
    ``path_constraints`` :class:`~ocpar.ocp.constraints.PathConstraint` objects of ``x`` and
    ``u`` (module docstring), compiled when the shape is built; ``solver_options`` IPOPT's
    own options over these (``ipopt.tol``, ``ipopt.linear_solver``, …;
    :mod:`ocpar.ocp.solver_options`), checked when the shape is built."""

    model: OdeModel
    elements: int
    order: int
    control_order: int
    control_bounds: tuple[tuple[float, float], ...]
    duration_bounds: tuple[float, float]
    final_components: tuple[int, ...] = ()
    terminal_cost: Callable[[ca.SX, ca.SX], ca.SX] | None = None
    running_cost: bool = True
    tol: float = 1e-10
    max_iter: int = 500
    path_constraints: tuple[PathConstraint | CompiledConstraint, ...] = ()
    solver_options: SolverOptions = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "solver_options", solver_options(self.solver_options))
        object.__setattr__(self, "path_constraints", compile_constraints(
            self.path_constraints, {"x": self.model.nx, "u": self.model.nu}))
        self.dynamics_shape()  # checks the grid, the bounds and the final components
        if self.terminal_cost is None and not self.running_cost:
            raise ValueError("a DFET OCP needs a cost: a terminal_cost, a running_cost or both")

    def dynamics_shape(self) -> DfetShape:
        """The weak-form equations' shape, with x_0 = 0 (x_0 enters them as a parameter)."""
        return DfetShape(self.model, self.elements, self.order, self.control_order,
                         self.control_bounds, self.duration_bounds, (0.0,) * self.model.nx,
                         tuple(self.final_components), (0.0,) * len(self.final_components))

    @property
    def n_params(self) -> int:
        """Length of p = (x_0, target)."""
        return self.model.nx + len(self.final_components)

    def build(self) -> DfetOcpTranscription:
        """The transcription of this shape (see :func:`~ocpar.ocp.transcription`)."""
        return DfetOcpTranscription(self)


@dataclass
class DfetSolution(InnerSolution):
    """Result of one DFET OCP solve: the common fields, and ``z`` the NLP solution (see
    :class:`~ocpar.ocp.dfet.DfetTranscription` to slice it), ``final_state`` x_f (nx,),
    ``final_time`` t_f, ``cost_gradient`` dJ*/dp (n_params, from the NLP multipliers) and
    ``lam_g`` the constraint multipliers."""

    z: np.ndarray
    final_state: np.ndarray
    final_time: float
    cost_gradient: np.ndarray
    lam_g: np.ndarray


class DfetOcpTranscription:
    """The DFET optimal control NLP of one shape and its IPOPT solver. A guess is a z."""

    def __init__(self, shape: DfetOcpShape) -> None:
        self.shape = shape
        self.dfet = dfet = DfetTranscription(shape.dynamics_shape())
        model, n, nx = shape.model, shape.elements, shape.model.nx
        self.nx, self.n_params = nx, shape.n_params
        p = ca.SX.sym("p", self.n_params)
        z = dfet.z
        # the first nx equations carry +x_0; the final conditions (shape's values 0) −target
        shift = ca.vertcat(p[:nx], ca.SX.zeros(dfet.ng - nx - len(shape.final_components)),
                           -p[nx:])
        x_f, t_f = dfet.final_state(z), dfet.final_time(z)
        cost = ca.SX(0) if shape.terminal_cost is None else shape.terminal_cost(x_f, t_f)
        _, sigma = dfet.quadrature
        if shape.running_cost:
            xs, us = ca.SX.sym("x", nx), ca.SX.sym("u", model.nu)
            rate = ca.Function("g", [xs, us], [model.running_cost(xs, us)]).map(sigma.size)
            weights = ca.DM(sigma).T
            total = ca.SX(0)
            for xq, uq in zip(dfet.quadrature_states, dfet.quadrature_controls, strict=True):
                total += ca.mtimes(weights, rate(xq, uq).T)
            cost += t_f / (2 * n) * total
        path = dfet.path_rows(shape.path_constraints)
        self.g = ca.vertcat(dfet.constraints + shift, path.expr)
        #: Constraint bounds: the weak form and final conditions = 0, then the path rows'.
        self.lbg = np.concatenate([np.zeros(dfet.ng), path.lower])
        self.ubg = np.concatenate([np.zeros(dfet.ng), path.upper])
        self.n_path = path.count
        self.cost, self.p, self.z = cost, p, z
        self.nz, self.ng = dfet.nz, dfet.ng + path.count

    @cached_property
    def solver_settings(self) -> dict[str, dict]:
        """The options this shape's solver is built with (defaults and the shape's
        ``solver_options``): ``ipopt``, ``nlpsol``'s."""
        # IPOPT relaxes inequalities by 1e-8 (relative) unless told not to
        exact = {"bound_relax_factor": 0.0} if self.n_path else {}
        return {"ipopt": ipopt(self.shape.solver_options, self.shape.tol, self.shape.max_iter,
                               **exact)}

    @cached_property
    def solver(self) -> ca.Function:
        """IPOPT solver of this shape, built on first use and then reused."""
        nlp = {"x": self.z, "p": self.p, "f": self.cost, "g": self.g}
        return ca.nlpsol("dfet_ocp", "ipopt", nlp, self.solver_settings["ipopt"])

    def default_guess(self, params: np.ndarray) -> np.ndarray:
        """States on the straight line in time from x_0 to the target (free components held
        at x_0), controls at 0 clipped into their bounds, t_f mid-way in its bounds."""
        params = np.asarray(params, float)
        shape, dfet, nx = self.shape, self.dfet, self.nx
        x0 = params[:nx]
        x_end = x0.copy()
        x_end[list(shape.final_components)] = params[nx:]
        n = shape.elements
        s = ((np.arange(n)[:, None] + (dfet.state_nodes + 1) / 2) / n).reshape(-1, 1)
        nodes = x0 + s * (x_end - x0)
        c_lo, c_hi = np.array(shape.control_bounds).T
        controls = np.tile(np.clip(0.0, c_lo, c_hi), n * (shape.control_order + 1))
        t_f = 0.5 * sum(shape.duration_bounds)
        return np.concatenate([nodes.ravel(), x_end, controls, [t_f]])

    def fallback_guesses(self, params: np.ndarray) -> Iterator[np.ndarray]:
        """None."""
        return iter(())

    def warm_start(self, solution: DfetSolution) -> np.ndarray:
        """The guess that re-solves from ``solution``: its z."""
        return solution.z

    def solve(self, params: np.ndarray, guess: np.ndarray | None = None,
              multipliers: np.ndarray | None = None) -> DfetSolution:
        """Solve for p = (x_0, target) from ``guess`` (default :meth:`default_guess`) and
        constraint multipliers (default 0); a failed solve is returned, not raised."""
        params = check_params(params, self.n_params, "DFET")
        z0 = self.default_guess(params) if guess is None else np.asarray(guess, float)
        dfet = self.dfet
        call = call_nlpsol(self.solver, x0=z0, p=params, lbx=dfet.lbz, ubx=dfet.ubz,
                           lbg=self.lbg, ubg=self.ubg,
                           lam_g0=0 if multipliers is None else multipliers)
        if call.out is None:
            return self.failure(params, call.status, call.solve_time_s)
        z = np.asarray(call.out["x"]).ravel()
        return DfetSolution(
            **call.common, z=z, final_state=dfet.final_state(z), final_time=dfet.final_time(z),
            cost_gradient=call.cost_gradient, lam_g=np.asarray(call.out["lam_g"]).ravel())

    def failure(self, params: np.ndarray, status: str, elapsed: float) -> DfetSolution:
        """A failed solve for p: NaN cost, z, gradient and multipliers, with ``status``."""
        return DfetSolution(cost=float("nan"), status=status, success=False, iterations=0,
                            attempts=1, solve_time_s=elapsed, z=np.full(self.nz, np.nan),
                            final_state=np.full(self.nx, np.nan), final_time=float("nan"),
                            cost_gradient=np.full(self.n_params, np.nan),
                            lam_g=np.full(self.ng, np.nan))


def dfet_ocp_problem(shape: DfetOcpShape) -> DfetOcpTranscription:
    """The process-wide DFET OCP transcription of ``shape`` (:func:`~ocpar.ocp.transcription`)."""
    return transcription(shape)
