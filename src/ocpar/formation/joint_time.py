"""Newton's method in the shift θ and the common final time T together: the free final
time's outer step (:func:`~ocpar.formation.final_time.solve_free_time`) where the
coupling's solutions form a one-parameter family φ(θ)
(:class:`~ocpar.formation.couplings.coupling.ShiftFamily`).

The objective is Φ(θ, T) = J(θ, T) + w T, J = Σ_i J_i*(z(φ_i(θ)), T). Each superstep solves
every agent at the current (θ, T), T a parameter of its inner problem set on the workers,
and returns the units' sums (:mod:`ocpar.formation.outer_step`): J, J_θ, J_θθ, J_T, J_TT and
J_θT, the T terms from each inner problem's multipliers and KKT system (envelope theorem).
So one superstep gives Φ's gradient and Hessian, and one Newton step moves θ and T together.

The step: where J > 0 falls in T and is convex in it (J_T < 0 < J_TT), Newton's step on
the equations J_θ / J = 0 and log(−J_T / w) = 0 in (θ, log T): for J = c(θ) T^k (point
masses from rest to rest: k = −3) the first does not depend on T and the second is linear
in log T (T exact in one step given θ); taken where d(J_θ / J)/dθ > 0 and it descends Φ.
Else Newton's step on ∇Φ = 0 where Φ's Hessian is positive definite; else θ and T each by
its own one-dimensional step. θ moves at most
:data:`~ocpar.formation.hierarchical.MAX_OFFSET_STEP`; T stays in [T_min, T_max] (at a
bound where J_T + w points outward it stays there and θ alone moves). A trial that raises
Φ beyond rounding, or whose inner solves fail, is rejected and the step halved. Converged
when |J_θ| ≤ ``tol`` Σ|g_i φ_i′| with J_θθ > 0 and |J_T + w| ≤ ``time_tol`` (|J_T| + w)
(or T at a bound pointing outward), or when no step longer than the tolerances lowers Φ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ocpar.formation.couplings.coupling import ShiftFamily
from ocpar.formation.feasibility import InnerSolveFailed
from ocpar.formation.hierarchical import MAX_OFFSET_STEP, ROUNDING_RTOL, OuterObjective
from ocpar.formation.outer_step import ShiftValues


@dataclass
class JointSearch:
    """Where :func:`joint_newton` stopped: the shift ``theta`` (rad) and ``duration`` T,
    the sums there (``values``), the Newton ``iterations``, ``success``, why it stopped
    (``reason``), the bound T sits at (``at_bound``: "T_min", "T_max" or None) and every
    superstep's (θ, T, J, J_T, J_TT) in ``history`` (a rejected trial marked)."""

    theta: float
    duration: float
    values: ShiftValues
    iterations: int
    success: bool
    reason: str
    at_bound: str | None = None
    history: list[dict] = field(default_factory=list)


def joint_newton(objective: OuterObjective, family: ShiftFamily, theta: float,
                 duration: float, weight: float, bounds: tuple[float, float], tol: float,
                 time_tol: float, max_iterations: int) -> JointSearch:
    """min over (θ, T) of Φ = J + w T from (``theta``, ``duration``) (module docstring),
    T in ``bounds`` (T_min, T_max), the agents of ``objective`` taking T as their last
    parameter. Raises :class:`InnerSolveFailed` where the first superstep's solves fail."""
    low, high = bounds
    history: list[dict] = []

    def evaluate(theta: float, duration: float) -> ShiftValues:
        try:
            values = objective.shifted(family, theta, duration)
        except InnerSolveFailed as exc:
            history.append({"theta": theta, "T": duration, "cost": None, "failed": str(exc)})
            raise
        history.append({"theta": theta, "T": duration, "cost": values.value,
                        "dcost_dT": values.time_slope, "d2cost_dT2": values.time_curvature})
        return values

    values = evaluate(theta, duration)
    merit = values.value + weight * duration
    shrink = 1.0
    n = objective.problem.agents
    for iteration in range(max_iterations):
        outward = _outward(values, duration, weight, low, high)
        time_met = outward is not None or abs(values.time_slope + weight) <= time_tol * (
            abs(values.time_slope) + weight)
        if time_met and abs(values.slope) <= tol * values.scale and values.curvature > 0:
            return JointSearch(theta, duration, values, iteration, True,
                               f"|dJ/dtheta| and |dJ/dT + w| below tolerance"
                               f"{'' if outward is None else f' (T at {outward})'}",
                               outward, history)
        d_theta, d_time = _step(values, duration, weight, n, outward is not None)
        d_theta, d_time = shrink * d_theta, shrink * d_time
        if abs(d_theta) > MAX_OFFSET_STEP:
            d_time *= MAX_OFFSET_STEP / abs(d_theta)
            d_theta = math.copysign(MAX_OFFSET_STEP, d_theta)
        trial = (theta + d_theta, float(np.clip(duration + d_time, low, high)))
        small = (abs(trial[0] - theta) <= tol * (1 + abs(theta))
                 and abs(trial[1] - duration) <= time_tol * duration)
        try:
            t_values = evaluate(*trial)
        except InnerSolveFailed:   # infeasible (or unsolved) there: a rejected step
            shrink /= 2
            if small:
                break
            continue
        t_merit = t_values.value + weight * trial[1]
        if t_merit <= merit + ROUNDING_RTOL * abs(merit):
            (theta, duration), values, merit, shrink = trial, t_values, t_merit, 1.0
            if small:
                return JointSearch(theta, duration, values, iteration + 1, True,
                                   "step in (theta, T) below tolerance",
                                   _outward(values, duration, weight, low, high), history)
        else:
            history[-1]["rejected"] = True
            shrink /= 2
            if small:
                return JointSearch(theta, duration, values, iteration + 1, True,
                                   "no step longer than the tolerance lowers J + w T",
                                   _outward(values, duration, weight, low, high), history)
    else:
        return JointSearch(theta, duration, values, max_iterations, False,
                           "iteration limit reached", None, history)
    return JointSearch(theta, duration, values, iteration + 1, False,
                       "the trials' inner solves fail however short the step", None, history)


def _outward(values: ShiftValues, duration: float, weight: float, low: float, high: float
             ) -> str | None:
    """"T_min" or "T_max" where T sits at that bound with J_T + w pointing out of
    [T_min, T_max], else None."""
    slope = values.time_slope + weight
    if duration <= low and slope >= 0:
        return "T_min"
    if duration >= high and slope <= 0:
        return "T_max"
    return None


def _step(values: ShiftValues, duration: float, weight: float, agents: int, pinned: bool
          ) -> tuple[float, float]:
    """The step (dθ, dT) at ``values`` (module docstring); dT = 0 where T is ``pinned`` at
    a bound."""
    g, h = values.slope, values.curvature
    theta_alone = -g / h if h > 0 else -(np.sign(g) or 1.0) * np.pi / agents
    if pinned:
        return theta_alone, 0.0
    g_t, h_t, cross, cost = values.time_slope, values.time_curvature, values.cross, values.value
    gradient = g_t + weight
    if cost > 0 and g_t < 0 < h_t:   # Newton on (J_θ / J, log(−J_T / w)) in (θ, log T)
        matrix = np.array([[(h * cost - g**2) / cost**2,
                            duration * (cross * cost - g * g_t) / cost**2],
                           [cross / g_t, duration * h_t / g_t]])
        with np.errstate(all="ignore"):
            d_theta, d_log = np.linalg.solve(matrix, [-g / cost, -math.log(-g_t / weight)]) \
                if np.linalg.det(matrix) != 0 else (math.nan, math.nan)
        d_time = duration * math.expm1(min(d_log, 700.0))
        if matrix[0, 0] > 0 and math.isfinite(d_theta) and math.isfinite(d_time) \
                and g * d_theta + gradient * d_time < 0:
            return float(d_theta), d_time
    if h > 0 and h_t > 0 and h * h_t > cross**2:   # Φ's Hessian positive definite
        det = h * h_t - cross**2
        return (-(h_t * g - cross * gradient) / det, -(h * gradient - cross * g) / det)
    # no Newton model of Φ: θ by its own step, T by the one-dimensional step on J_T + w
    # (:func:`next_duration`), else doubled or halved towards J_T + w = 0
    new = next_duration(duration, g_t, h_t, weight)
    if not math.isfinite(new):
        new = 2 * duration if gradient < 0 else duration / 2
    return theta_alone, new - duration


def next_duration(duration: float, gradient: float, curvature: float, weight: float
                  ) -> float:
    """The Newton step's T for J_T + w = 0 given J_T (``gradient``) and J_TT
    (``curvature``): in log–log coordinates where J decreases and is convex (log(−J_T) =
    log w, linear in log T: exact in one step for J ∝ T^k, e.g. point masses from rest to
    rest, k = −3), else on J_T + w itself; NaN where neither applies."""
    if gradient < 0 and curvature > 0:
        order = duration * curvature / gradient   # d log(−J_T) / d log T < 0
        return duration * (weight / -gradient) ** (1 / order)
    if curvature > 0:
        return duration - (gradient + weight) / curvature
    return math.nan


__all__ = ["JointSearch", "joint_newton", "next_duration"]
