"""The optimal ordering's proof for linear–quadratic ODE agents: six Clohessy–Wiltshire
spacecraft (:mod:`ocpar.examples.formation_cw`), checked against a brute force over all
720 assignments whose inner costs are computed here by another method: the closed-form
least-norm optimum of the RK4-discretised linear system (numpy), not the package's NLP."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import casadi as ca
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from ocpar.bsp.serial import SerialBackend
from ocpar.examples import formation_cw
from ocpar.formation import FormationProblem
from ocpar.formation.ordering import optimal_ordering
from ocpar.models import ClohessyWiltshire, Unicycle
from ocpar.ocp import MsEndpointShape
from ocpar.ocp.constraints import PathConstraint
from ocpar.ocp.reach import end_cost_convexity

#: The brute force's grid of offsets per slot width (each assignment's best then polished).
GRID = 64


def _random_starts() -> np.ndarray:
    """Six start states scattered about the V-bar, moving (m, m/min), out of plane too."""
    rng = np.random.default_rng(46)
    starts = np.zeros((6, 6))
    starts[:, 0] = rng.uniform(-60, 60, 6)
    starts[:, 1] = rng.uniform(-500, -250, 6)
    starts[:, 2] = rng.uniform(-40, 40, 6)
    starts[:, 3:] = rng.uniform(-2, 2, (6, 3))
    return starts


class ClosedForm:
    """Each agent's optimum ending at z(φ) on the circle, at rest or (a free end velocity)
    with the velocity minimised out, in closed form: the
    least-norm controls U of x_N = Φᴺ x_0 + Σ_j Φᴺ⁻¹⁻ʲ Γ u_j, J = h Σ_j |u_j|² (RK4 of
    ẋ = A x + B u with u constant on an interval: Φ = Σ_{k≤4} (hA)ᵏ/k!,
    Γ = h Σ_{k≤3} (hA)ᵏ/(k+1)! B, and RK4's quadrature of |u|² is h |u|²)."""

    def __init__(self, problem) -> None:
        shape = problem.common_shape
        n_motion, self.h, steps = shape.model.mean_motion, \
            shape.duration / shape.intervals, shape.intervals
        a = np.zeros((6, 6))
        a[:3, 3:] = np.eye(3)
        a[3, 0], a[3, 4], a[4, 3], a[5, 2] = 3 * n_motion**2, 2 * n_motion, -2 * n_motion, \
            -n_motion**2
        b = np.vstack([np.zeros((3, 3)), np.eye(3)])
        powers = [np.linalg.matrix_power(self.h * a, k) for k in range(5)]
        phi = sum(p / math.factorial(k) for k, p in enumerate(powers))
        gamma = self.h * sum(p / math.factorial(k + 1) for k, p in enumerate(powers[:4])) @ b
        # the end rows fixed: all six, or the position alone where the velocity is free
        self.rows = [i for i in range(6) if i not in shape.free_end]
        self.g = np.hstack([np.linalg.matrix_power(phi, steps - 1 - j) @ gamma
                            for j in range(steps)])[self.rows]               # (rows, 3N)
        self.weight = np.linalg.inv(self.g @ self.g.T)
        self.drift = (problem.starts @ np.linalg.matrix_power(phi, steps).T)[:, self.rows]
        self.radius = problem.curve.radius

    def _gaps(self, angles: np.ndarray) -> np.ndarray:
        """x_N − Φᴺ x_0 in the fixed rows (6 agents, len(angles), rows): at rest at z(φ)."""
        ends = np.zeros((len(angles), 6))
        ends[:, 0], ends[:, 1] = self.radius * np.cos(angles), self.radius * np.sin(angles)
        return ends[None, :, self.rows] - self.drift[:, None, :]

    def costs(self, angles: np.ndarray) -> np.ndarray:
        """Ĵ (6, len(angles)) of each agent ending at each angle (rad)."""
        r = self._gaps(angles)
        return self.h * np.einsum("ima,ab,imb->im", r, self.weight, r)

    def max_thrust(self, angles: np.ndarray) -> np.ndarray:
        """The largest |u_j[k]| (6, len(angles)), over intervals and axes, of the least-norm
        controls."""
        u = np.einsum("ka,ab,imb->imk", self.g.T, self.weight, self._gaps(angles))
        return np.abs(u).max(axis=-1)


def brute_force(problem) -> tuple[float, list[np.ndarray]]:
    """(min over the 720 assignments σ and offsets θ of Σ_i Ĵ_i(θ + 2π σ(i)/6), the angles
    (6,) of every assignment within 1e-9 of it: ties, e.g. by a symmetry of the starts):
    each assignment's best offset on a grid of :data:`GRID` per slot width, polished by
    bounded Brent."""
    costs = ClosedForm(problem).costs
    n = problem.agents
    width = 2 * np.pi / n
    grid = np.linspace(0.0, width, GRID + 1)
    table = costs((grid[None, :] + width * np.arange(n)[:, None]).ravel()).reshape(
        n, n, GRID + 1)                                                     # agent, slot, θ
    best = []
    for sigma in itertools.permutations(range(n)):
        slots = np.array(sigma)
        values = table[np.arange(n), slots].sum(axis=0)
        k = int(np.argmin(values))
        polish = minimize_scalar(
            lambda t, s=slots: float(costs(t + width * s).diagonal().sum()),
            bounds=(grid[max(k - 1, 0)], grid[min(k + 1, GRID)]), method="bounded",
            options={"xatol": 1e-12})
        theta = polish.x if polish.fun < values[k] else grid[k]
        best.append((min(polish.fun, values[k]), theta + width * slots))
    optimum = min(value for value, _ in best)
    return optimum, [phi for value, phi in best if value <= optimum * (1 + 1e-9)]


@pytest.fixture(scope="module")
def backend():
    return SerialBackend()


def _free_velocity(problem: FormationProblem) -> FormationProblem:
    """``problem`` with the end velocity free (the spacecraft arrive moving)."""
    shape = problem.common_shape
    return FormationProblem(
        name="cw-free-velocity", curve=problem.curve, starts=problem.starts,
        shape=MsEndpointShape(shape.model, intervals=shape.intervals,
                              duration=shape.duration, free_end=(3, 4, 5)),
        final_state=np.full(3, np.nan))


@pytest.mark.parametrize("case", ["v-bar", "scattered", "free end velocity"])
def test_six_cw_spacecraft_ordering_is_proven_and_brute_force(backend, case):
    problem = formation_cw.make(starts=_random_starts() if case == "scattered" else None)
    if case == "free end velocity":
        problem = _free_velocity(problem)
    result = optimal_ordering(problem, backend)
    assert result.bound == "quadratic" and result.proven and result.gap <= 1e-9
    optimum, optima = brute_force(problem)
    assert abs(result.total_cost - optimum) <= 1e-9 * optimum
    assert result.lower_bound <= optimum * (1 + 1e-12)   # the proven bound is a bound
    # the same formation as one of the optima (the V-bar train has tied pairs)
    apart = [np.max(np.abs(np.angle(np.exp(1j * (result.phi - phi))))) for phi in optima]
    assert min(apart) <= 1e-6


def test_cw_ordering_under_a_thrust_box_is_proven_by_planes(backend):
    """The convex path (supporting planes from solves, sqpmethod inner solves) under a box
    |u_j[k]| ≤ 2.5 m/min² that binds at some ends on the circle but not at the free
    optimum: that optimum is feasible, so it is the limited fleet's too."""
    box = 2.5
    free = formation_cw.make()
    shape = MsEndpointShape(free.common_shape.model, intervals=free.common_shape.intervals,
                            duration=free.common_shape.duration,
                            control_bounds=((-box, box),) * 3)
    problem = FormationProblem(name="cw-box", shape=shape, curve=free.curve,
                               starts=free.starts)
    result = optimal_ordering(problem, backend)
    assert result.bound == "convex" and result.proven and result.gap <= 1e-9
    optimum, optima = brute_force(free)
    closed = ClosedForm(free)
    assert all(np.max(np.diagonal(closed.max_thrust(phi))) < box for phi in optima)
    assert np.max(closed.max_thrust(np.linspace(0, 2 * np.pi, 60))) > box
    assert abs(result.total_cost - optimum) <= 1e-9 * optimum


@dataclass(frozen=True)
class _Costly(ClohessyWiltshire):
    """Clohessy–Wiltshire with another running cost: ``kind`` ``indefinite`` (|u|² − |x|²)
    or ``linear`` (|u|² + x: unbounded below)."""

    kind: str = "indefinite"

    def running_cost(self, x: ca.SX, u: ca.SX) -> ca.SX:
        return ca.sumsqr(u) - (ca.sumsqr(x) if self.kind == "indefinite" else -x[0])


def test_end_cost_convexity_of_ode_agents():
    cw = ClohessyWiltshire()
    assert end_cost_convexity(MsEndpointShape(cw)) == "quadratic"
    assert end_cost_convexity(MsEndpointShape(cw, control_bounds=((-1.0, 1.0),) * 3)) \
        == "convex"
    norm = PathConstraint(lambda u: ca.sumsqr(u), upper=4.0, name="thrust")
    assert end_cost_convexity(MsEndpointShape(cw, path_constraints=(norm,))) == "convex"
    box_x = PathConstraint(lambda x: x[0], upper=10.0, name="radial")
    assert end_cost_convexity(MsEndpointShape(cw, path_constraints=(box_x,))) is None
    assert end_cost_convexity(MsEndpointShape(Unicycle())) is None   # nonlinear rhs
    assert end_cost_convexity(MsEndpointShape(_Costly(kind="indefinite"))) is None
    assert end_cost_convexity(MsEndpointShape(_Costly(kind="linear"))) is None
