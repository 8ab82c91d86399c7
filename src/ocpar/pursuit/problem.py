"""The pursuit problem (the local-pursuit paper's Problem 1 with no Mayer term):

    min Σ_j h g(x_j, u_j) + w T   s.t.   x_{j+1} = Φ_h(x_j, u_j),  x_0 = x_I,
                                         x_N[i] = target_i (i ∈ S),

with N samples over [0, T] (h = T/(N−1)), state and control bounds from the model, and agent 0's
feasible plan. T is fixed (the ``duration``, w = 0) or free in [T_min, T_max] (``final_time``,
w the ``time_weight``; agent 0's plan then runs over the ``duration``). Everything is checked
when the problem is built: one ValueError naming the field.
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike
from scipy.integrate import solve_ivp

from ocpar.models.ode import OdeModel, check_ode_model, control_bounds, ode_functions
from ocpar.ocp.batch import BufferedFunction
from ocpar.ocp.constraints import (
    CompiledConstraint,
    PathConstraint,
    check_smooth,
    compile_constraints,
)
from ocpar.ocp.multiple_shooting import INTEGRATORS, check_final_time, step_function

#: Accuracy of the integration of a control law for agent 0 (scipy's RK45).
LAW_RTOL, LAW_ATOL = 1e-11, 1e-13
#: The integration's largest step, as a fraction of the horizon.
LAW_MAX_STEP_FRACTION = 1 / 600
#: How far agent 0's plan may break a path constraint (in the constraint's unit).
PATH_TOLERANCE = 1e-9


@dataclass(frozen=True)
class FinalValue:
    """A named function of the final state that a run reports, e.g. the final mass in kg:
    ``of_state`` maps x(T) (nx,) to a float. ``larger_is_better`` says which way an
    improvement goes when it is the problem's headline."""

    name: str
    unit: str
    of_state: Callable[[np.ndarray], float]
    larger_is_better: bool = False

    @property
    def key(self) -> str:
        """Its ``result.json`` key: name and unit in snake case, e.g. ``final_mass_kg``."""
        return snake_case(f"{self.name} {self.unit}")


@dataclass(frozen=True)
class ControlLaw:
    """Agent 0's plan as a control law: ``law(t)`` gives u (nu,) at time t (the model's time
    unit). It is integrated accurately from x_I (RK45, rtol 1e-11) and sampled on the grid;
    its controls are taken at the grid points t_0..t_{N−2}."""

    law: Callable[[float], ArrayLike]


@dataclass(frozen=True, eq=False)
class SampledPlan:
    """Agent 0's plan as samples: ``states`` (N, nx) with states[0] = x_I, ``controls``
    (N−1, nu), control j held on [t_j, t_{j+1})."""

    states: np.ndarray
    controls: np.ndarray


@dataclass(frozen=True, eq=False)
class PursuitProblem:
    """An optimal control problem for pursuit-based multiple shooting.

    ``model`` the ODE with its running cost and bounds (:class:`ocpar.models.OdeModel`);
    ``duration`` T and ``samples`` N (h = T/(N−1)); ``initial_state`` x_I (nx,);
    ``target_components`` the indices S of the final state that are fixed (one up to all) and
    ``target`` their values (len(S),); ``plan`` agent 0's feasible plan; ``headline`` what a run
    reports first and stops on (None: the cost, smaller is better); ``cost_name`` and
    ``cost_unit`` name Σ h g; ``checks`` final-state values also reported for the result's
    controls re-simulated accurately; ``integrator`` Φ_h, ``"euler"`` or ``"rk4"``;
    ``path_constraints`` :class:`~ocpar.ocp.constraints.PathConstraint` objects of ``x`` and
    ``u`` that every agent's trajectory meets (at the samples, as
    :class:`~ocpar.ocp.MsShape` imposes them; agent 0's plan must meet them too);
    ``final_time`` (T_min, T_max): a free final time T in these bounds (model's time unit;
    None: T = ``duration``, fixed), agent 0's plan then runs over ``duration`` (within them),
    and ``time_weight`` w ≥ 0 adds w T to the cost (w = 1 with a zero running cost: minimum
    time). A free final time is solved by the full-horizon MS (``mode="ms"``); the train
    refuses it (:func:`~ocpar.pursuit.solve.check_mode`).
    """

    model: OdeModel
    duration: float
    samples: int
    initial_state: np.ndarray
    target_components: tuple[int, ...]
    target: np.ndarray
    plan: ControlLaw | SampledPlan
    name: str = "pursuit"
    headline: FinalValue | None = None
    cost_name: str = "cost"
    cost_unit: str = ""
    checks: tuple[FinalValue, ...] = field(default=())
    integrator: str = "euler"
    path_constraints: tuple[PathConstraint | CompiledConstraint, ...] = ()
    final_time: tuple[float, float] | None = None
    time_weight: float = 0.0

    def __post_init__(self) -> None:
        check_ode_model(self.model)
        nx = self.model.nx
        object.__setattr__(self, "path_constraints", compile_constraints(
            self.path_constraints, {"x": nx, "u": self.model.nu}))
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name: must be a non-empty string, got {self.name!r}")
        if not (isinstance(self.duration, numbers.Real) and math.isfinite(self.duration)
                and self.duration > 0):
            raise ValueError(f"duration: must be a finite number > 0, got {self.duration!r}")
        if not isinstance(self.samples, int | np.integer) or self.samples < 3:
            raise ValueError(f"samples: must be an integer >= 3, got {self.samples!r}")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"integrator: {self.integrator!r} is not one of {INTEGRATORS}")
        self._check_final_time()
        lower, upper = self.model.state_bounds()
        lower, upper = np.asarray(lower, float), np.asarray(upper, float)
        x0 = as_array("initial_state", self.initial_state, (nx,))
        require_within("initial_state", x0, lower, upper)
        comps = tuple(self.target_components)
        if (not comps or len(set(comps)) != len(comps)
                or not all(isinstance(i, int | np.integer) and 0 <= i < nx for i in comps)):
            raise ValueError(f"target_components: need distinct indices in 0..{nx - 1}, one up "
                             f"to all of them, got {self.target_components!r}")
        comps = tuple(int(i) for i in comps)
        target = as_array("target", self.target, (len(comps),))
        require_within("target", target, lower[list(comps)], upper[list(comps)])
        object.__setattr__(self, "initial_state", x0)
        object.__setattr__(self, "target_components", comps)
        object.__setattr__(self, "target", target)
        first_control = self._check_plan()
        self._check_model_values(first_control)
        named = [("headline", self.headline)] if self.headline is not None else []
        named += [(f"checks[{k}]", value) for k, value in enumerate(self.checks)]
        for label, value in named:
            check_final_value(label, value, x0)
        for label in ("cost_name", "cost_unit"):
            if not isinstance(getattr(self, label), str):
                raise ValueError(f"{label}: must be a string")

    def _check_final_time(self) -> None:
        """A free final time's bounds hold the plan's ``duration``; a time weight needs one."""
        if not (isinstance(self.time_weight, numbers.Real) and math.isfinite(self.time_weight)
                and self.time_weight >= 0):
            raise ValueError(f"time_weight: must be a finite number >= 0, got "
                             f"{self.time_weight!r}")
        if self.final_time is None:
            if self.time_weight:
                raise ValueError("time_weight: applies only to a free final time (final_time)")
            return
        lower, upper = check_final_time(self.final_time)
        if not lower <= self.duration <= upper:
            raise ValueError(f"duration: agent 0's horizon {self.duration!r} must lie within "
                             f"final_time {(lower, upper)}")
        object.__setattr__(self, "final_time", (lower, upper))

    def _check_plan(self) -> np.ndarray:
        """Check agent 0's plan (shapes, finiteness, bounds, x_I); return its first control."""
        nx, nu, n = self.model.nx, self.model.nu, self.samples
        u_lower, u_upper = control_bounds(self.model)
        if isinstance(self.plan, ControlLaw):
            if not callable(self.plan.law):
                raise ValueError("plan.law: must be a function of t")
            u0 = evaluate_law(self.plan.law, 0.0, nu)
            require_within("plan.law(0)", u0, u_lower, u_upper)
            return u0
        if not isinstance(self.plan, SampledPlan):
            raise ValueError(f"plan: must be a ControlLaw or a SampledPlan, got "
                             f"{type(self.plan).__name__}")
        states = as_array("plan.states", self.plan.states, (n, nx))
        controls = as_array("plan.controls", self.plan.controls, (n - 1, nu))
        if not np.allclose(states[0], self.initial_state, rtol=1e-12, atol=1e-12):
            raise ValueError("plan.states: the first sample must be initial_state")
        lower, upper = self.model.state_bounds()
        require_within("plan.states", states, np.asarray(lower, float), np.asarray(upper, float))
        require_within("plan.controls", controls, u_lower, u_upper)
        self.check_path_constraints("plan", states, controls)
        object.__setattr__(self, "plan", SampledPlan(states, controls))
        return controls[0]

    def _check_model_values(self, u0: np.ndarray) -> None:
        """f and g must be finite at x_I and agent 0's first control."""
        for label, function in zip(("model.rhs", "model.running_cost"), self._functions,
                                   strict=True):
            value = np.asarray(function(self.initial_state, u0), float)
            if not np.isfinite(value).all():
                raise ValueError(f"{label}: not finite at initial_state and agent 0's first "
                                 "control")

    @cached_property
    def _functions(self) -> tuple[Any, Any]:
        return ode_functions(self.model)

    @property
    def free_time(self) -> bool:
        """Whether the final time is free (``final_time`` given)."""
        return self.final_time is not None

    @property
    def step(self) -> float:
        """h = T/(N−1) of agent 0's plan (T = ``duration``), in the model's time unit."""
        return self.duration / (self.samples - 1)

    @property
    def grid(self) -> np.ndarray:
        """Agent 0's sample times t_j = j h, (N,)."""
        return np.arange(self.samples) * self.step

    def times(self, final_time: float | None = None) -> np.ndarray:
        """Sample times j T/(N−1) (N,) of a trajectory of horizon ``final_time`` T (default
        ``duration``: :attr:`grid`; not finite: :attr:`grid` too, a failed solve's)."""
        horizon = self.horizon(final_time)
        if not math.isfinite(horizon):
            return self.grid
        return np.arange(self.samples) * (horizon / (self.samples - 1))

    def horizon(self, final_time: float | None = None) -> float:
        """The horizon T of a trajectory: ``final_time``, or ``duration`` when None."""
        return self.duration if final_time is None else float(final_time)

    @property
    def headline_name(self) -> str:
        return self.cost_name if self.headline is None else self.headline.name

    @property
    def headline_unit(self) -> str:
        return self.cost_unit if self.headline is None else self.headline.unit

    @property
    def headline_key(self) -> str:
        """The headline's ``result.json`` key, e.g. ``final_mass_kg``."""
        return snake_case(f"{self.headline_name} {self.headline_unit}")

    @property
    def cost_key(self) -> str:
        """The cost's ``result.json`` key, e.g. ``fuel_kg``."""
        return snake_case(f"{self.cost_name} {self.cost_unit}")

    def cost(self, x: np.ndarray, u: np.ndarray, final_time: float | None = None) -> float:
        """The cost of states x (N, nx) and controls u (N−1, nu) over the horizon
        ``final_time`` T (default ``duration``) as multiple shooting integrates it:
        h Σ_j g(x_j, u_j) with Euler, each step's RK4 quadrature with RK4
        (:func:`~ocpar.ocp.multiple_shooting.step_function`), h = T/(N−1); plus w T."""
        horizon = self.horizon(final_time)
        step = horizon / (self.samples - 1)
        phi = step_function(self.model, step, self.integrator).map(len(u))
        rates = phi(np.asarray(x)[:-1].T, np.asarray(u).T)[1]
        return float(step * np.sum(np.asarray(rates))) + self.time_weight * horizon

    def headline_value(self, x: np.ndarray, u: np.ndarray,
                       final_time: float | None = None) -> float:
        """The headline of a trajectory of horizon ``final_time`` (default ``duration``): its
        final value, or its cost."""
        if self.headline is None:
            return self.cost(x, u, final_time)
        return float(self.headline.of_state(np.asarray(x)[-1]))

    def improvement(self, previous: float, current: float) -> float:
        """How much a headline ``current`` improves on ``previous`` (> 0: better)."""
        larger = self.headline is not None and self.headline.larger_is_better
        return current - previous if larger else previous - current

    def feasible_trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """Agent 0: states (N, nx) and controls (N−1, nu) (copies)."""
        x, u = self._agent0
        return x.copy(), u.copy()

    @cached_property
    def _agent0(self) -> tuple[np.ndarray, np.ndarray]:
        if isinstance(self.plan, SampledPlan):
            return self.plan.states, self.plan.controls
        return self._integrate_law()

    def _integrate_law(self) -> tuple[np.ndarray, np.ndarray]:
        """The control law integrated accurately, sampled on the grid; its controls at the
        grid points. Raises ValueError naming ``plan`` if the integration fails or leaves the
        bounds."""
        rhs, law, nu = BufferedFunction(self._functions[0]), self.plan.law, self.model.nu
        sol = solve_ivp(
            lambda t, x: rhs(x, evaluate_law(law, t, nu))[0],
            (0.0, self.duration), self.initial_state, t_eval=self.grid, rtol=LAW_RTOL,
            atol=LAW_ATOL, max_step=self.duration * LAW_MAX_STEP_FRACTION,
        )
        if not sol.success or sol.y.shape[1] != self.samples or not np.isfinite(sol.y).all():
            raise ValueError(f"plan: integrating the control law failed ({sol.message})")
        x = sol.y.T.copy()
        u = np.array([evaluate_law(law, t, nu) for t in self.grid[:-1]])
        lower, upper = self.model.state_bounds()
        require_within("plan (integrated states)", x, np.asarray(lower, float),
                       np.asarray(upper, float))
        require_within("plan.law", u, *control_bounds(self.model))
        self.check_path_constraints("plan (integrated states)", x, u)
        return x, u

    def path_violation(self, x: np.ndarray, u: np.ndarray) -> float:
        """The largest excess of the path constraints over their bounds along states x
        (N, nx) and controls u (N−1, nu), where :class:`~ocpar.ocp.MsShape` imposes them
        (0.0 without constraints; NaN where a row is not finite)."""
        excess = [0.0]
        for constraint in self.path_constraints:
            points = ({"x": x[:-1], "u": u} if constraint.depends_on("u") else {"x": x[1:]})
            excess.append(float(np.max(constraint.violation(points))))
        return max(excess) if not np.isnan(excess).any() else float("nan")

    def check_path_constraints(self, label: str, x: np.ndarray, u: np.ndarray) -> None:
        """ValueError naming ``label`` and the constraint unless the trajectory x (N, nx),
        u (N−1, nu) meets every path constraint (to 1e-9), with finite values and Jacobians
        (the first window's solve starts there), and the initial state those of x alone."""
        for i, constraint in enumerate(self.path_constraints):
            check_smooth(constraint, {"x": x[:-1], "u": u},
                         f"path_constraints[{i}] ({constraint.name})",
                         [f"{label} sample {j}" for j in range(len(u))])
            if not constraint.depends_on("u"):
                at_start = constraint.violation({"x": x[:1]})[0]
                if not at_start <= PATH_TOLERANCE:
                    raise ValueError(f"initial_state: breaks path_constraints[{i}] "
                                     f"({constraint.name}) by {at_start:.3g}")
            points = ({"x": x[:-1], "u": u} if constraint.depends_on("u") else {"x": x[1:]})
            excess = constraint.violation(points)
            if not np.all(excess <= PATH_TOLERANCE):
                j = int(np.argmax(np.nan_to_num(excess, nan=np.inf)))
                raise ValueError(f"{label}: breaks path_constraints[{i}] ({constraint.name}) "
                                 f"at sample {j} by {excess[j]:.3g}")


def snake_case(text: str) -> str:
    """``"final mass kg"`` → ``"final_mass_kg"``; ``"cost "`` → ``"cost"``."""
    return re.sub(r"\W+", "_", text.strip().lower()).strip("_")


def as_array(label: str, value: object, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` as a finite float array of ``shape``, or one ValueError naming ``label``."""
    try:
        array = np.array(value, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{label}: not an array of numbers") from None
    if array.shape != shape:
        raise ValueError(f"{label}: shape {array.shape}, expected {shape}")
    if not np.isfinite(array).all():
        raise ValueError(f"{label}: contains non-finite values")
    return array


def require_within(label: str, value: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> None:
    """One ValueError naming ``label`` if ``value`` (…, n) leaves [lower, upper] (n,)."""
    outside = (value < lower) | (value > upper)
    if outside.any():
        index = np.argwhere(outside)[0]
        raise ValueError(f"{label}: value {value[tuple(index)]:g} at index {tuple(index.tolist())} "
                         f"is outside the model's bounds")


def evaluate_law(law: Callable[[float], ArrayLike], t: float, nu: int) -> np.ndarray:
    """u = law(t) as a finite (nu,) array, or one ValueError naming ``plan.law``."""
    try:
        value = law(t)
    except Exception as exc:
        raise ValueError(f"plan.law: fails at t = {t:g}: {type(exc).__name__}: {exc}"
                         .splitlines()[0]) from None
    return as_array(f"plan.law({t:g})", value, (nu,))


def check_final_value(label: str, value: object, x0: np.ndarray) -> None:
    """A FinalValue whose function gives a finite number at ``x0``, or one ValueError."""
    if not isinstance(value, FinalValue):
        raise ValueError(f"{label}: must be a FinalValue, got {type(value).__name__}")
    try:
        number = float(value.of_state(x0.copy()))
    except Exception as exc:
        raise ValueError(f"{label}.of_state: fails at initial_state: {type(exc).__name__}: "
                         f"{exc}".splitlines()[0]) from None
    if not math.isfinite(number):
        raise ValueError(f"{label}.of_state: not finite at initial_state")
    if not snake_case(f"{value.name} {value.unit}"):
        raise ValueError(f"{label}.name: must name the value")

