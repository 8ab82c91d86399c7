"""The result of a formation run, as an object and as ``result.json``."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ocpar.formation.couplings.potential import equidistance_error
from ocpar.formation.keep_out.obstacles import Clearance
from ocpar.formation.keep_out.separation import ClosestApproach
from ocpar.formation.verify import Verification
from ocpar.results import RunResult


@dataclass
class FormationResult(RunResult):
    """Outcome of :func:`ocpar.formation.solve_formation`.

    ``phi`` (n,) final angles (rad); ``agent_costs`` (n,) inner optimal costs Ĵ_i;
    ``trajectories`` (n, N+1, nq) DMOC node paths; ``controls`` (n, N, nu) their interval
    controls (``result.json`` carries each agent's ``peak_thrust`` max_k |u_k|, force
    unit); ``cost_parts`` the total cost split by
    control groups where the model names them (e.g. ``translational_cost``,
    ``rotational_cost``); ``coupling_residual``
    max_k |c_k(φ)|, the scaled coupling c = (ℓ²/n³) dG/dφ as the outer problem imposes it
    (:mod:`ocpar.formation.couplings.potential`), at the parameters located from the returned end
    points (``verification``: :class:`~ocpar.formation.verify.Verification`, whose checks
    decide whether the run may say ``converged``; ``result.json`` carries it and
    ``near_collision``); ``on_circle`` whether the curve is a circle (the
    equidistance error is NaN otherwise); ``separation`` the closest approach of any two
    agents on the continuous paths (:meth:`FormationProblem.closest_approach
    <ocpar.formation.FormationProblem.closest_approach>`); with a required minimum
    separation (:mod:`ocpar.formation.keep_out.rounds`): ``required_separation`` D,
    ``separation_rounds`` the keep-out rounds run and ``unconstrained_cost`` the total cost
    before them (NaN/None/0 without); with obstacles (:mod:`ocpar.formation.keep_out.obstacles`, in
    every inner problem): ``obstacle_clearance`` the smallest clearance of any agent from
    any obstacle on the returned continuous paths (which agent, obstacle, when) and
    ``obstacle_sides`` on which side each agent passes each obstacle
    (:func:`~ocpar.formation.keep_out.obstacles.passing_sides`: per agent, per obstacle ``left`` or
    ``right`` in 2-D, a unit vector in 3-D, None for a half-space); ``feasible_set``
    ``continuous`` on a circle (a common rotation), ``discrete`` elsewhere (the potential's
    isolated critical points), with ``critical_sets`` the candidates searched by
    ``--ordering optimal`` (:meth:`~ocpar.formation.couplings.critical_sets.CriticalSet.to_dict`,
    cheapest first; None when none were).
    The common fields are :class:`ocpar.results.RunResult`'s.
    """

    scheme: ClassVar[str] = "formation"
    #: Null in ``result.json`` unless converged (with the cost parts, :meth:`headline_keys`).
    headline_fields: ClassVar[tuple[str, ...]] = ("total_cost", "agent_costs",
                                                  "unconstrained_cost")

    agents: int
    mode: str
    total_cost: float
    phi: np.ndarray
    agent_costs: np.ndarray
    trajectories: np.ndarray
    outer_iterations: int
    separation: ClosestApproach
    cost_parts: dict[str, float] = field(default_factory=dict)
    coupling_residual: float = math.nan
    on_circle: bool = True
    required_separation: float | None = None
    separation_rounds: int = 0
    unconstrained_cost: float = math.nan
    controls: np.ndarray | None = None
    obstacle_clearance: Clearance | None = None
    obstacle_sides: list[list[str | list[float] | None]] | None = None
    feasible_set: str = "continuous"
    critical_sets: list[dict] | None = None
    verification: Verification | None = None

    def headline_keys(self) -> tuple[str, ...]:
        """:attr:`headline_fields` and the cost parts' keys."""
        return self.headline_fields + tuple(self.cost_parts)

    def headline_title(self) -> str:
        """The total cost, for the plot's title (:meth:`~ocpar.results.RunResult.title`)."""
        return f"total cost {self.total_cost:.6e}"

    @property
    def peak_thrust(self) -> np.ndarray:
        """max_k |u_k| per agent (n,), force unit (NaN without controls)."""
        if self.controls is None:
            return np.full(self.agents, np.nan)
        return np.max(np.linalg.norm(np.asarray(self.controls, float), axis=2), axis=1)

    @property
    def equidistance_error(self) -> float:
        """max |gap − 2π/n| between neighbours on the circle (rad); NaN off a circle."""
        return equidistance_error(self.phi) if self.on_circle else math.nan

    def scheme_fields(self) -> dict:
        """Formation's fields of ``result.json`` (per-agent costs, final angles, paths)."""
        return {
            "agents": self.agents,
            "mode": self.mode,
            "total_cost": _finite_or_none(self.total_cost),
            **{name: _finite_or_none(value) for name, value in self.cost_parts.items()},
            "phi": np.asarray(self.phi, float).tolist(),
            "equidistance_error": _finite_or_none(self.equidistance_error),
            "coupling_residual": _finite_or_none(self.coupling_residual),
            "outer_iterations": self.outer_iterations,
            "min_separation": _finite_or_none(self.separation.distance),
            "closest_pair": (list(self.separation.agents)
                             if math.isfinite(self.separation.distance) else None),
            "closest_time": _finite_or_none(self.separation.time),
            "required_separation": self.required_separation,
            "separation_rounds": self.separation_rounds,
            "unconstrained_cost": _finite_or_none(self.unconstrained_cost),
            "agent_costs": [_finite_or_none(c) for c in self.agent_costs],
            "peak_thrust": [_finite_or_none(t) for t in self.peak_thrust],
            **self._obstacle_fields(),
            "feasible_set": self.feasible_set,
            "critical_sets": self.critical_sets,
            **self._verification_fields(),
            "trajectories": np.asarray(self.trajectories, float).tolist(),
        }

    def _verification_fields(self) -> dict:
        """``verification`` (:meth:`~ocpar.formation.verify.Verification.to_dict`) and
        ``near_collision`` (None unless there is one); none without a verification."""
        v = self.verification
        if v is None:
            return {}
        return {"verification": v.to_dict(), "near_collision": v.near_collision}

    def _obstacle_fields(self) -> dict:
        """``min_obstacle_clearance`` and where it occurs, ``obstacle_sides`` (none without
        obstacles)."""
        c = self.obstacle_clearance
        if c is None:
            return {}
        return {"min_obstacle_clearance": _finite_or_none(c.distance),
                "obstacle_agent": c.agent if c.agent >= 0 else None,
                "obstacle_index": c.obstacle if c.obstacle >= 0 else None,
                "obstacle_time": _finite_or_none(c.time),
                "obstacle_sides": self.obstacle_sides}

    def _required_summary(self) -> str:
        """The summary's words on a required separation ('' without one)."""
        if self.required_separation is None:
            return ""
        if not self.converged:
            return f"   required {self.required_separation:g}: {self.separation_rounds} round(s)"
        increase = self.total_cost / self.unconstrained_cost - 1
        return (f"   required {self.required_separation:g}: {self.separation_rounds} round(s), "
                f"cost {increase * 100:+.3g}% over the unconstrained {self.unconstrained_cost:.6e}")

    def _obstacle_summary(self) -> str:
        """The summary's line on obstacles ('' without any)."""
        c = self.obstacle_clearance
        if c is None:
            return ""
        return (f"min obstacle clearance {c.distance:.6g} (agent {c.agent}, obstacle "
                f"{c.obstacle} at t = {c.time:.6g}; obstacles in the inner problems)\n")

    def summary(self) -> str:
        """A few lines for people: the headline numbers of the run."""
        equidistance = (f"equidistance error {self.equidistance_error:.1e} rad   "
                        if self.on_circle else "")
        parts = "".join(f"{name.replace('_', ' ')} {value:.6e}   "
                        for name, value in self.cost_parts.items())
        cost = (f"total cost {self.total_cost:.12e}   {parts}" if self.converged
                else f"total cost — {self.not_reached()}\n")
        return (
            f"status {self.status} ({self.message})\n"
            f"{cost}"
            f"{equidistance}coupling residual {self.coupling_residual:.1e}\n"
            f"min separation {self.separation.distance:.6g} (agents "
            f"{self.separation.agents[0]} and {self.separation.agents[1]} at t = "
            f"{self.separation.time:.6g})"
            f"{self._required_summary()}\n"
            f"{self._obstacle_summary()}"
            f"outer iterations {self.outer_iterations}   supersteps {self.supersteps}   "
            f"inner solves {self.inner_solves} (failed {self.failed_solves}, retries "
            f"{self.retries})\n"
            f"wall time {self.wall_time_s:.2f} s on {self.workers} {self.backend} worker(s), "
            f"mode {self.mode}"
        )


def _finite_or_none(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None
