"""The result of a pursuit run, as an object and as ``result.json``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ocpar.models.labels import DIMENSIONLESS, Labels
from ocpar.results import Array, RunResult, array, components, time_axes


@dataclass
class PursuitResult(RunResult):
    """Outcome of :func:`ocpar.pursuit.solve_pursuit`.

    The headline (named by the problem: ``headline_name`` in ``headline_unit``, written to
    ``result.json`` under ``headline_key``, e.g. the final mass in kg; NaN, as ``cost`` is,
    unless the run converged: then in ``last_iterate``) of the result, of every
    finished agent (``headlines``, agent 0 first) and of the full-horizon MS solution when
    computed; ``cost`` Σ h g (under ``cost_key``); ``rk_checks`` the problem's checks of the
    re-simulated final state by key; with PBMS, ``stop_reason`` (one of
    :data:`~ocpar.pursuit.slp.STOP_REASONS`), ``estimated_remaining`` the headline's
    improvement still to come and ``remaining_method`` how it was obtained: ``extrapolated``
    from the agents' recent rate (``inf`` while the gains do not shrink;
    :func:`~ocpar.pursuit.slp.remaining_improvement`) or ``certified``, the gap to
    ``certificate_headline``, the full-horizon MS optimum solved from the train's trajectory
    (:class:`~ocpar.pursuit.slp.PursuitTrain`; of the finest level). ``x`` (N, nx)
    and ``u`` (N−1, nu) are the result trajectory, ``initial_x`` agent 0's, ``reference_x``
    the full-horizon MS solution's. ``agents`` counts every level's agents,
    ``agents_per_level`` coarsest first (:func:`~ocpar.pursuit.slp.run_levels`); ``headlines``
    are the finest level's. The answer (``x``, ``u``, the headline, the cost) comes from
    ``result_source``: ``train`` (its last agent) or ``full_horizon`` (the certificate, when it
    is at least as good); the train's own figures are kept beside it (``train_headline``,
    ``train_cost``, ``train_remaining`` and ``train_remaining_method``; its agents are
    ``agents``), with ``windows`` the (N_Δ, N_δ) it ran with, widened after each stall, and
    the settings it was given (``window``, ``update``, ``epsilon``, ``levels``; None in
    ``ms`` mode, which uses none of them, and left out of its ``result.json``).
    ``time`` (N,) the sample times t_j of the answer, in real time (the model's time unit,
    ``time_unit``): j T/(N−1) with ``final_time`` T, the problem's duration or, with
    ``free_final_time``, the T found (``plan_time`` (N,) agent 0's sample times); ``states``
    and ``controls`` the names and units of the model's entries
    (:mod:`ocpar.models.labels`; None: the defaults). Wall times in s.
    """

    scheme: ClassVar[str] = "pursuit"

    samples: int
    mode: str
    headline_key: str
    headline_name: str
    headline_unit: str
    headline: float
    cost_key: str
    cost: float
    agents: int
    subproblem_solves: int
    max_agents_in_flight: int
    constraint_violation: float
    rk_terminal_error: float
    rk_checks: dict[str, float]
    x: np.ndarray
    u: np.ndarray
    initial_x: np.ndarray
    time: np.ndarray
    headlines: list[float] = field(default_factory=list)
    reference_headline: float | None = None
    reference_x: np.ndarray | None = None
    stop_reason: str | None = None
    estimated_remaining: float | None = None
    remaining_method: str | None = None
    certificate_headline: float | None = None
    agents_per_level: list[int] = field(default_factory=list)
    result_source: str | None = None
    train_headline: float | None = None
    train_cost: float | None = None
    train_remaining: float | None = None
    train_remaining_method: str | None = None
    windows: list[tuple[int, int]] = field(default_factory=list)
    window: int | None = None
    update: int | None = None
    epsilon: float | None = None
    levels: int | None = None
    time_unit: str = DIMENSIONLESS
    final_time: float | None = None
    free_final_time: bool = False
    plan_time: np.ndarray | None = None
    states: Labels | None = None
    controls: Labels | None = None
    #: the common count of inner solves is the catch-up (and full-horizon) solves
    inner_solves: int = field(init=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        self.inner_solves = self.subproblem_solves

    @property
    def peak_rss_mb_per_worker(self) -> float:
        """Largest peak resident memory of any worker process during the run (MiB)."""
        return max((m for t in self.trace for m in t.worker_peak_rss_mb), default=0.0)

    def label(self, value: float) -> str:
        """``value`` of the headline with its name and unit, e.g. 'final mass 0.47 kg'."""
        unit = f" {self.headline_unit}" if self.headline_unit else ""
        return f"{self.headline_name} {value:.6f}{unit}"

    def headline_title(self) -> str:
        """The returned headline, for the plots' titles (:meth:`~ocpar.results.RunResult.title`)."""
        return self.label(self.headline) + self.final_time_text()

    def final_time_text(self) -> str:
        """', final time T <unit>' with a free final time, else ''."""
        if not self.free_final_time:
            return ""
        unit = "" if self.time_unit == DIMENSIONLESS else f" {self.time_unit}"
        return f", final time {self.final_time:.6f}{unit}"

    def headline_attributes(self) -> tuple[str, ...]:
        """``headline`` and ``cost``: NaN unless converged (the last iterate's in
        ``last_iterate``; the train's own figures stay, named as the train's)."""
        return ("headline", "cost")

    def headline_keys(self) -> tuple[str, ...]:
        """The headline figure's and the cost's keys (null unless converged; the per-agent
        figures stay: they are the train's history); a free final time's T too."""
        return (self.headline_key, self.cost_key) + (
            ("final_time",) if self.free_final_time else ())

    def scheme_fields(self) -> dict:
        """Pursuit's fields of ``result.json`` (the trajectories and the per-agent headlines
        are in the array file, :meth:`arrays`). Keys
        named by the problem: ``headline`` gives the headline's key (e.g. ``final_mass_kg``),
        which also prefixes ``reference_ms_``; the cost's key (e.g.
        ``fuel_kg``); ``rk_`` + each check's key."""
        key = self.headline_key
        return {
            "samples": self.samples,
            "mode": self.mode,
            "final_time": self.final_time,
            "free_final_time": self.free_final_time,
            **self.train_settings(),
            "headline": key,
            "headline_name": self.headline_name,
            "headline_unit": self.headline_unit,
            key: self.headline,
            self.cost_key: self.cost,
            "agents": self.agents,
            "agents_per_level": self.agents_per_level,
            "subproblem_solves": self.subproblem_solves,
            "max_agents_in_flight": self.max_agents_in_flight,
            "constraint_violation": self.constraint_violation,
            "rk_terminal_error": self.rk_terminal_error,
            **{f"rk_{name}": value for name, value in self.rk_checks.items()},
            "peak_rss_mb_per_worker": self.peak_rss_mb_per_worker,
            f"reference_ms_{key}": self.reference_headline,
            "stop_reason": self.stop_reason,
            "remaining_method": self.remaining_method,
            f"certificate_ms_{key}": self.certificate_headline,
            # JSON has no infinity: null while the gains do not shrink
            f"estimated_remaining_{key}": finite_or_none(self.estimated_remaining),
            "result_source": self.result_source,
            f"train_{self.cost_key}": self.train_cost,
            f"train_{key}": self.train_headline,
            "train_agents": self.agents if self.mode == "pbms" else None,
            f"train_remaining_{key}": finite_or_none(self.train_remaining),
            "train_remaining_method": self.train_remaining_method,
            "windows": [list(w) for w in self.windows],
        }

    def train_settings(self) -> dict:
        """PBMS's settings ``window`` N_Δ, ``update`` N_δ, ``epsilon`` and ``levels``; none
        in ``ms`` mode, which uses none of them."""
        if self.mode != "pbms":
            return {}
        return {"window": self.window, "update": self.update, "epsilon": self.epsilon,
                "levels": self.levels}

    def arrays(self) -> dict[str, Array]:
        """The array file's variables: the coordinates ``time`` (N) the sample times,
        ``interval_time`` (N−1) the start t_j of each control interval
        (:func:`~ocpar.results.time_axes`), ``state_component`` and
        ``control_component`` (the model's names, with their ``*_units``); ``state`` (time,
        state_component) the returned trajectory; ``control`` (interval_time,
        control_component) its controls, u_j on [t_j, t_{j+1}]; ``initial_state``
        (state_component) x_I; ``plan_state`` (time, state_component) agent 0's trajectory;
        ``reference_state`` the full-horizon MS solution's (when solved); ``agent_headline``
        (agent) the headline of each of the finest level's finished agents, agent 0 first
        (a cost-headline problem: its cost); with a free final time ``plan_time`` (time)
        agent 0's sample times (``time`` is the answer's). Units: the model's
        (:mod:`ocpar.models.labels`) and the headline's."""
        x, u = np.asarray(self.x, float), np.asarray(self.u, float)
        states = self.states or Labels(tuple(f"x{i}" for i in range(x.shape[1])),
                                       (DIMENSIONLESS,) * x.shape[1])
        controls = self.controls or Labels(tuple(f"u{i}" for i in range(u.shape[1])),
                                           (DIMENSIONLESS,) * u.shape[1])
        initial = np.asarray(self.initial_x, float)
        out = (time_axes(self.time, self.time_unit)
               | components("state_component", states, "state entry")
               | components("control_component", controls, "control entry")
               | {
            "state": array("time state_component", x, states, "returned trajectory x(t_j)"),
            "control": array("interval_time control_component", u, controls,
                             "returned control u_j (on [t_j, t_{j+1}])"),
            "initial_state": array("state_component", initial[0], states,
                                   "initial state x_I"),
            "plan_state": array("time state_component", initial, states,
                                "agent 0's trajectory (its plan)"),
            "agent_headline": array("agent", np.asarray(self.headlines, float),
                                    self.headline_unit or DIMENSIONLESS,
                                    f"{self.headline_name} of each finished agent "
                                    "(finest level)"),
        })
        if self.free_final_time and self.plan_time is not None:
            out["plan_time"] = array("time", np.asarray(self.plan_time, float), self.time_unit,
                                     "agent 0's sample times (its horizon is the plan's)")
        if self.reference_x is not None:
            out["reference_state"] = array("time state_component", self.reference_x,
                                           states, "full-horizon MS solution's trajectory")
        return out

    def summary(self) -> str:
        unit = f" {self.headline_unit}" if self.headline_unit else ""
        ref = ("" if self.reference_headline is None
               else f"   (full-horizon MS: {self.reference_headline:.6f}{unit})")
        checks = "".join(f", {name} {value:.4g}" for name, value in self.rk_checks.items())
        cost = (f", {self.cost_key} {self.cost:.6f}" if self.headline_key != self.cost_key
                else "")  # the cost only where the headline is another figure
        if self.converged:
            cost += self.final_time_text()
        figures = (f"{self.headline_name} {self.headline:.6f}{unit}{cost}" if self.converged
                   else f"{self.headline_name} — {self.not_reached()}")
        if self.result_source == "full_horizon":
            ref += (f"\nreturned: the full-horizon MS from the train's trajectory; the train's "
                    f"last agent {self.train_headline:.6f}{unit}")
        return (
            f"status {self.status} ({self.message})\n"
            f"{figures}{ref}\n"
            f"agents {self.agents}   subproblem solves {self.subproblem_solves} "
            f"(failed {self.failed_solves}, retries {self.retries})   "
            f"supersteps {self.supersteps}   "
            f"max in flight {self.max_agents_in_flight}\n"
            f"constraint violation {self.constraint_violation:.1e}   RK re-simulation: "
            f"terminal error {self.rk_terminal_error:.3g}{checks}\n"
            f"wall time {self.wall_time_s:.2f} s on {self.workers} {self.backend} worker(s), "
            f"peak memory per worker {self.peak_rss_mb_per_worker:.0f} MiB"
        )


def finite_or_none(value: float | None) -> float | None:
    """``value``, or None (JSON null) if it is None or infinite (JSON has no infinity)."""
    return None if value is None or np.isinf(value) else value
