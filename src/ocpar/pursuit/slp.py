"""Sampled local pursuit (SLP) with multiple-shooting subproblems: PBMS, pipelined.

Agent 0 follows the feasible trajectory. Agent k leaves x_I at kΔ; at each of its update
times (every δ) it solves, by multiple shooting,

* a **catch-up** problem while its leader has not reached S_Q: a fixed-time Δ transfer from
  its own state to the leader's current state, in the target set's components only (on the
  orbit transfer, r, ṙ, θ̇: were the leader's mass a terminal constraint, every path would burn
  the same fuel), or
* a **free-running** problem once the leader is in S_Q: to S_Q over its remaining time,

and applies the first δ of the plan. Each subproblem is warm-started from the leader's plan
at the same update index (same shape; primal and multipliers): ~3 IPOPT iterations instead
of ~4 from the leader's trajectory. With Δ = (N_Δ−1)h, δ = N_δ h, the catch-up problem has
N_Δ samples; in local sample indices, agent k's update at index j needs its leader's states up
to index j + N_Δ − 1 (the leader is Δ ahead in time).

The train stops when the headline's improvement still to come is below ε, or after
``max_agents`` agents. What is still to come is extrapolated from the agents' recent gains
(:func:`remaining_improvement`) until that estimate first falls below ε; then, where the
horizon fits one worker (N ≤ ``certify_samples``), the full-horizon MS problem is solved once
from the last agent's trajectory (:func:`full_horizon_task`, one superstep) and what is still
to come is measured against its optimum from then on: the train stops when it is within ε of
it (the stop reason says which rule fired; :data:`STOP_REASONS`). With ``finish=
"full_horizon"`` (the default) the certificate is solved as soon as the train's first agent
has finished, and the run ends there. Either way the run returns the better of the train's
last agent and the certificate (:func:`conclude`, :data:`RESULT_SOURCES`), certifies a budget
stop too, and widens the windows of a train that has stalled (:data:`STALL_RATIO`,
:func:`widen`).
With ``levels`` L > 1 the train runs first on a grid 2^(L−1) times coarser, then on grids
twice as fine, each from the coarser result (:func:`run_levels`).

All agents whose next update has what it needs (from earlier supersteps) solve in one
superstep, so about (N−1)/(N_Δ−1) agents run in parallel. The computation is the SLP of the
paper whatever the schedule: each update depends only on data fixed by the rules, so results
do not depend on the backend or the worker count.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ocpar.bsp import Backend
from ocpar.models.ode import control_bounds
from ocpar.ocp import MsShape, MsSolution, OcpTask, solve_task, solve_tasks
from ocpar.ocp.multiple_shooting import LOCAL_SOLVERS
from ocpar.ocp.solver_options import SOLVER_OPTIONS_HELP, solver_options
from ocpar.options import option
from ocpar.pursuit.problem import PursuitProblem, SampledPlan
from ocpar.pursuit.validate import discrete_residual

#: How a run whose horizon fits (N ≤ ``certify_samples``) finishes (``PursuitSettings.finish``).
FINISHES = ("full_horizon", "train")


@dataclass(frozen=True)
class PursuitSettings:
    """SLP settings: ``window`` N_Δ (samples per catch-up problem), ``update`` N_δ (samples
    applied per update), ``epsilon`` the stopping threshold on the improvement of the
    problem's headline still to come (in the headline's unit; see the module docstring),
    ``max_agents`` a bound on the number of pursuing agents (per level), ``levels`` the
    coarse-to-fine levels (:func:`run_levels`; 1: the paper's scheme), ``certify_samples``
    the largest N whose stop is certified by a full-horizon MS solve (module docstring; 0:
    never), ``local_solver`` the subproblems' solver from the leader's plan (IPOPT if it
    fails; see :class:`~ocpar.ocp.MsShape`), ``finish`` how a run whose horizon fits ends
    (:data:`FINISHES`: the full-horizon MS after the first agent, or the paper's train);
    ``solver_options`` the inner solvers' own options by ``SOLVER.NAME``
    (:mod:`ocpar.ocp.solver_options`: ``ipopt.*``, ``sqpmethod.*``, ``qrqp.*``, ``newton.*``)
    of every multiple-shooting NLP, checked when the settings are made."""

    window: int = option(60, "samples per catch-up problem N_Δ (Δ = (N_Δ-1)h)", low=2,
                         metavar="N_DELTA")
    update: int = option(32, "samples applied per update N_δ (δ = N_δ h)", low=1,
                         metavar="N_UPDATE")
    epsilon: float = option(1e-3, "stop when the improvement of the headline still to come "
                            "(certified by the full-horizon MS, or estimated from the agents' "
                            "recent rate) is below EPS (in the headline's unit, kg for the "
                            "orbit transfer)",
                            above=0, metavar="EPS")
    max_agents: int = option(100_000, "stop after this many agents (per level, widened "
                             "windows included); where N <= --certify-samples the stop is "
                             "certified and the better answer returned, otherwise it exits 1",
                             low=2)
    levels: int = option(1, "coarse-to-fine levels L: PBMS first on (N-1)/2^(L-1)+1 samples, "
                         "then on grids twice as fine, each starting from the coarser result "
                         "(agent 0); 1: the paper's scheme", low=1)
    certify_samples: int = option(10_001, "largest N on which the stop is certified: once the "
                                  "extrapolated estimate is below EPS, the full-horizon MS "
                                  "(one NLP on one worker) is solved from the train's "
                                  "trajectory and the train stops within EPS of its optimum; "
                                  "0: stop on the extrapolated estimate", low=0, metavar="N")
    local_solver: str = option("newton", "subproblems' solver from the leader's plan: newton "
                               "(Newton steps on the KKT system) or sqp (CasADi sqpmethod, "
                               "qrqp); IPOPT if it fails", choices=LOCAL_SOLVERS)
    finish: str = option("full_horizon", "where N <= --certify-samples: full_horizon: stop once "
                         "the full-horizon MS solved from the train's trajectory (first tried "
                         "after agent 1) succeeds, and return it; train: the train goes on "
                         "until it is itself within EPS of that optimum (the paper's scheme, "
                         "certified); either way the better answer is returned",
                         choices=FINISHES)
    solver_options: dict = option(  # noqa: RUF009 (option() is a dataclass field)
        default_factory=dict, help=SOLVER_OPTIONS_HELP + "; of every multiple-shooting NLP "
        "(the agents' and the full horizon's)", flag="--solver-option",
        metavar="SOLVER.NAME=VALUE", dotted=True)

    def __post_init__(self) -> None:
        object.__setattr__(self, "solver_options", dict(solver_options(self.solver_options)))

    def check(self, samples: int) -> None:
        """Raise ValueError unless 1 ≤ N_δ < N_Δ < N."""
        if not 2 <= self.window < samples:
            raise ValueError(f"window N_Δ must satisfy 2 <= N_Δ < N = {samples}, got {self.window}")
        if not 1 <= self.update < self.window:
            raise ValueError(f"update N_δ must satisfy 1 <= N_δ < N_Δ = {self.window}, "
                             f"got {self.update}")
        if not (self.epsilon > 0 and np.isfinite(self.epsilon)):
            raise ValueError(f"epsilon must be a positive number, got {self.epsilon}")
        if self.max_agents < 2:
            raise ValueError(f"max_agents must be at least 2, got {self.max_agents}")
        if self.certify_samples < 0:
            raise ValueError(f"certify_samples must be at least 0, got {self.certify_samples}")
        if self.levels < 1:
            raise ValueError(f"levels must be at least 1, got {self.levels}")
        factor = 2 ** (self.levels - 1)
        if (samples - 1) % factor or (samples - 1) // factor + 1 <= self.window:
            raise ValueError(f"levels {self.levels}: N - 1 = {samples - 1} must be divisible by "
                             f"{factor} and the coarsest grid, (N-1)/{factor}+1 samples, finer "
                             f"than N_Δ = {self.window}")
        if self.local_solver not in LOCAL_SOLVERS:
            raise ValueError(f"local_solver must be one of {LOCAL_SOLVERS}, got "
                             f"{self.local_solver!r}")
        if self.finish not in FINISHES:
            raise ValueError(f"finish must be one of {FINISHES}, got {self.finish!r}")


#: Fewest agent-to-agent improvements :func:`remaining_improvement` estimates from.
MIN_GAINS = 8
#: Why a run stopped (``result.json``'s ``stop_reason``), said of the answer it returns:
#: within ε of the certificate's optimum (the answer is the certificate itself, or the train
#: came within ε of it), the extrapolated estimate below ε (no certificate: N >
#: ``certify_samples``, or every attempt failed), or the agent budget spent without either.
STOP_REASONS = ("certified_within_epsilon", "estimate_below_epsilon", "max_agents")
#: Where the returned answer comes from (``result.json``'s ``result_source``): the train's last
#: agent, or the full-horizon MS solved from the train's trajectory (the certificate).
RESULT_SOURCES = ("train", "full_horizon")
#: A train has stalled when the certificate's improvement still to come is more than
#: STALL_RATIO times what its recent gains, continued as a geometric series
#: (:func:`remaining_improvement`), can still close: a train whose windows are shorter than an
#: arc where a constraint is active converges to a point above the optimum, its gains
#: shrinking geometrically (van der Pol with x2 ≥ −0.41 on a 0.75 s arc and 0.5 s windows:
#: 1.05e-2 left when the estimate says 1e-4, a ratio that only grows), while a slow but
#: converging train stays within a few times its estimate (the paper's case 2 at N = 501:
#: 3.5). A stalled train widens its windows (:func:`widen`) and goes on.
STALL_RATIO = 10.0
#: Largest discrete residual (continuity, target set, path constraints' excess; each in its
#: own unit) a certificate may have to be accepted, and a returned answer to be converged.
FEASIBILITY_TOL = 1e-8
#: How the reported improvement still to come was obtained (``remaining_method``).
REMAINING_METHODS = ("extrapolated", "certified")


def remaining_improvement(progress: Sequence[float]) -> float:
    """The improvement still to come, estimated from the recent rate. ``progress[i]`` is how
    much agent i + 1 improves on agent 1 (0 first; non-decreasing by Theorem 1), so its k
    increments are the successive agents' gains. The gains of the last quarter of the agents,
    S = progress[k] − progress[k − w] (w = k // 4), and of the quarter before, S', are
    continued as a geometric series: S ρ/(1 − ρ) with ρ = S/S'.

    Exact when the gains decay geometrically; an underestimate when they decay more slowly
    (the diffusion-like descent of a long horizon, or a slower mode taking over:
    :class:`PursuitTrain` certifies it where it can); ``inf`` while the gains do not shrink
    (ρ ≥ 1) or with fewer than :data:`MIN_GAINS` gains; 0 when the last quarter brought no
    improvement.
    """
    k = len(progress) - 1
    if k < MIN_GAINS:
        return float("inf")
    w = k // 4
    recent = progress[k] - progress[k - w]
    before = progress[k - w] - progress[k - 2 * w]
    if recent <= 0:
        return 0.0
    if recent >= before:
        return float("inf")
    ratio = recent / before
    return recent * ratio / (1 - ratio)


def full_horizon_shape(problem: PursuitProblem, options: Mapping[str, Any] | None = None
                       ) -> MsShape:
    """The full-horizon MS NLP's shape, with the solver ``options``."""
    return MsShape(problem.model, problem.samples - 1, problem.step, problem.target_components,
                   problem.integrator, path_constraints=problem.path_constraints,
                   final_time=problem.final_time, time_weight=problem.time_weight,
                   solver_options=solver_options(options))


def window_shape(problem: PursuitProblem, settings: PursuitSettings, intervals: int) -> MsShape:
    """An agent's subproblem shape with ``intervals`` intervals: warm-started by the
    settings' local solver, with their solver options."""
    return MsShape(problem.model, intervals, problem.step, problem.target_components,
                   problem.integrator, warm_start=True, local_solver=settings.local_solver,
                   path_constraints=problem.path_constraints,
                   solver_options=solver_options(settings.solver_options))


def full_horizon_task(problem: PursuitProblem, x: np.ndarray, u: np.ndarray,
                      fallback: tuple[np.ndarray, np.ndarray] | None = None,
                      options: Mapping[str, Any] | None = None) -> OcpTask:
    """Plain multiple shooting over [0, T] with N samples (one NLP, IPOPT) from the trajectory
    ``x`` (N, nx), ``u`` (N−1, nu); ``fallback`` a second (x, u) to start from if that fails;
    ``options`` the solver options (``PursuitSettings.solver_options``). With a free final time
    T is free within its bounds (the guesses' T: ``duration``)."""
    shape = full_horizon_shape(problem, options)

    def guess(x: np.ndarray, u: np.ndarray) -> np.ndarray:
        horizon = [problem.duration] if problem.free_time else []
        return np.concatenate([np.asarray(x)[1:].ravel(), np.asarray(u).ravel(), horizon])

    return OcpTask(shape, np.concatenate([problem.initial_state, problem.target]), guess(x, u),
                   fallback=None if fallback is None else guess(*fallback))


@dataclass
class Agent:
    """One agent's sampled trajectory on its own clock: states ``x`` (N, nx) known up to
    index ``position``, controls ``u`` (N−1, nu) applied so far, and the plans it solved at
    each update index, kept until its follower has used them as warm starts."""

    index: int
    x: np.ndarray
    u: np.ndarray
    position: int = 0
    solves: int = 0
    plans: dict[int, MsSolution] = field(default_factory=dict)

    @property
    def done(self) -> bool:
        return self.position == len(self.x) - 1


@dataclass(frozen=True)
class Certificate:
    """The full-horizon MS problem solved from agent ``agent``'s trajectory (the train's index
    over all its stages): its ``headline``, states ``x`` (N, nx) and controls ``u`` (N−1, nu)."""

    agent: int
    headline: float
    x: np.ndarray
    u: np.ndarray


@dataclass
class PursuitOutcome:
    """What the pursuit loop returns: the answer, states ``x`` (N, nx) and controls ``u``
    (N−1, nu), taken from ``result_source`` (one of :data:`RESULT_SOURCES`: the train's last
    agent ``best``, or the certificate when it is better); every finished agent's headline
    (agent 0 first, every stage); the train's own last headline ``train_headline`` and its
    improvement still to come ``train_remaining`` (``train_remaining_method``); counters
    (``subproblem_solves`` with the certificates) and status: whether the answer is within ε
    (``converged``), why the run stopped (one of :data:`STOP_REASONS`, said of the answer), the
    answer's improvement still to come (``remaining``, in the headline's unit; 0 for the
    certificate itself), how it was obtained (``remaining_method``, one of
    :data:`REMAINING_METHODS`) and the certificate (None without one). ``windows`` the
    (N_Δ, N_δ) of each stage, widened after a stall (:func:`widen`)."""

    best: Agent
    x: np.ndarray
    u: np.ndarray
    result_source: str
    headlines: list[float]
    train_headline: float
    train_remaining: float
    train_remaining_method: str
    subproblem_solves: int
    failed_solves: int
    retries: int
    max_in_flight: int
    converged: bool
    message: str
    stop_reason: str
    remaining: float
    remaining_method: str
    certificate: Certificate | None
    failures: list[str] = field(default_factory=list)
    #: agents of each level, coarsest first (:func:`run_levels`)
    agents_per_level: list[int] = field(default_factory=list)
    windows: list[tuple[int, int]] = field(default_factory=list)


class PursuitTrain:
    """The coordinator's state: agents in flight, each one's leader, the finished agents'
    headlines. A train widened after a stall (:func:`run_pursuit`) starts from the stalled
    train's last agent with ``agents_before`` agents already run and its ``certificate``."""

    def __init__(self, problem: PursuitProblem, settings: PursuitSettings,
                 certificate: Certificate | None = None, agents_before: int = 0) -> None:
        settings.check(problem.samples)
        #: Fewest intervals a problem to the target set needs: as many controls as fixed
        #: components (⌈|S| / nu⌉).
        self.min_intervals = -(-len(problem.target_components) // problem.model.nu)
        self.problem, self.settings = problem, settings
        self.agents_before = agents_before
        n = problem.samples
        x0, u0 = problem.feasible_trajectory()
        self.initial = Agent(0, x0, u0, position=n - 1)
        self.best = self.initial
        self._shapes: dict[int, MsShape] = {}
        self._target_index = np.array(problem.target_components)
        self.leaders: dict[int, Agent] = {0: self.initial}
        self.in_flight: list[Agent] = []
        self.headlines = [problem.headline_value(x0, u0)]
        self.solves = 0
        self.retries = 0
        self.failed = 0
        self.failures: list[str] = []
        self.launched = 0
        #: how much each finished agent improves on agent 1 (agent 1 first)
        self.progress: list[float] = []
        #: the improvement still to come, and how it was obtained (:data:`REMAINING_METHODS`)
        self.remaining, self.remaining_method = float("inf"), REMAINING_METHODS[0]
        #: the extrapolated estimate after the last finished agent
        self.estimate = float("inf")
        #: the full-horizon MS solved from the train's trajectory, once solved; None before
        self.certificate = certificate
        #: whether the train stopped on a stall (its windows to be widened)
        self.stalled = False
        #: certificate attempts made (by trigger), and why the last one failed ("" if none)
        self._tried: set[str] = set()
        self._certificate_failure = ""

    @property
    def _fits(self) -> bool:
        """Whether the full horizon fits one worker (N ≤ ``certify_samples``)."""
        return self.problem.samples <= self.settings.certify_samples

    def _shape(self, intervals: int) -> MsShape:
        """The subproblem shape with ``intervals`` intervals (made once per train)."""
        shape = self._shapes.get(intervals)
        if shape is None:
            shape = self._shapes[intervals] = window_shape(self.problem, self.settings,
                                                           intervals)
        return shape

    def _new_agent(self) -> Agent:
        n, nx = self.problem.samples, self.problem.model.nx
        self.launched += 1
        x = np.full((n, nx), np.nan)
        x[0] = self.problem.initial_state
        return Agent(self.launched, x, np.full((n - 1, self.problem.model.nu), np.nan))

    def ready(self) -> list[tuple[Agent, OcpTask]]:
        """Agents whose next update can be computed now, with their subproblems; launches a
        new agent when the last one has gone far enough for it to start."""
        n, window = self.problem.samples, self.settings.window
        last = self.in_flight[-1] if self.in_flight else self.initial
        if (self.agents_before + self.launched < self.settings.max_agents
                and last.position >= window - 1):
            agent = self._new_agent()
            self.leaders[agent.index] = last
            self.in_flight.append(agent)
        work = []
        for agent in self.in_flight:
            if agent.done:
                continue
            leader, j = self.leaders[agent.index], agent.position
            free_running = j >= n - window
            if free_running and not leader.done:
                continue
            if not free_running and leader.position < j + window - 1:
                continue
            end = n - 1 if free_running else j + window - 1
            target = (self.problem.target if free_running
                      else leader.x[end, self._target_index])
            plan = leader.plans.pop(j, None)
            trajectory = np.concatenate([leader.x[j + 1 : end + 1].ravel(),
                                         leader.u[j:end].ravel()])
            if plan is not None and len(plan.u) == end - j and plan.success:
                guess, lam = plan.w, plan.lam_g  # the leader's plan and multipliers
            else:  # agent 0 has no plans: its trajectory, no multipliers
                guess, lam = trajectory, None
            # the failure policy: a failed solve is retried from the leader's trajectory
            task = OcpTask(self._shape(end - j), np.concatenate([agent.x[j], target]), guess,
                           lam, fallback=trajectory)
            work.append((agent, task))
        return work

    def apply(self, agent: Agent, sol: MsSolution) -> None:
        """Move ``agent`` along the first δ of its plan (or to its end), never leaving
        fewer than :attr:`min_intervals` to go: a plan to the target set is then followed to
        its end, a catch-up plan for fewer steps."""
        self.solves += 1
        self.retries += sol.attempts - 1
        agent.solves += 1
        j, last = agent.position, len(agent.x) - 1
        steps = min(self.settings.update, len(sol.u))
        if 0 < last - (j + steps) < self.min_intervals:
            to_target = j + len(sol.u) == last
            steps = len(sol.u) if to_target else max(1, last - j - self.min_intervals)
        if sol.success:
            agent.plans[j] = sol
            agent.x[j + 1 : j + steps + 1] = sol.x[1 : steps + 1]
            agent.u[j : j + steps] = sol.u[:steps]
        else:  # failed after its retry: this update follows the leader's trajectory
            self.failed += 1
            self.failures.append(f"agent {agent.index} at sample {j}: {sol.status}")
            leader = self.leaders[agent.index]
            agent.x[j + 1 : j + steps + 1] = leader.x[j + 1 : j + steps + 1]
            agent.u[j : j + steps] = leader.u[j : j + steps]
        agent.position = j + steps

    def retire_finished(self, solve: Callable[[OcpTask], MsSolution]) -> str | None:
        """Take finished agents off the train in order; return the train's stop message when
        it stops (within ε of the certificate, or of the estimate without one; the
        certificate solved with ``finish="full_horizon"``; a stall, :attr:`stalled`; the agent
        budget spent), else None. ``solve`` solves the full-horizon certificate
        (:meth:`certify`) when it falls due: after the train's first agent with
        ``finish="full_horizon"``, when the estimate first falls below ε (the paper's train,
        ``finish="train"``: so that the certificate does not change where it stops) and at a
        budget stop without one, wherever the horizon fits."""
        while self.in_flight and self.in_flight[0].done:
            agent = self.in_flight.pop(0)
            self.headlines.append(self.problem.headline_value(agent.x, agent.u))
            self.leaders.pop(agent.index, None)
            self.best = agent
            if agent.index >= 1:  # agent 0 does not end on S_Q: progress from agent 1 on
                self.progress.append(self.problem.improvement(self.headlines[1],
                                                              self.headlines[-1]))
                stop = self._judge(agent, solve)
                if stop is not None:
                    return stop
        return None

    def _judge(self, agent: Agent, solve: Callable[[OcpTask], MsSolution]) -> str | None:
        """Update :attr:`remaining` after ``agent`` (certifying when due) and return the
        train's stop message if it stops there."""
        settings, eps = self.settings, self.settings.epsilon
        self.estimate = remaining_improvement(self.progress)
        full_horizon = settings.finish == FINISHES[0]
        if full_horizon:
            self._try_certificate("first", agent, solve)
        if self.estimate < eps:
            self._try_certificate("estimate", agent, solve)
        self._measure()
        total = self.agents_before + agent.index
        unit = f" {self.problem.headline_unit}".rstrip()
        name = self.problem.headline_name
        if full_horizon and self.certificate is not None:
            return f"full-horizon finish after agent {total}"
        if self.remaining < eps:
            if self.certificate is not None:
                return (f"the train came within {self.remaining:.2e}{unit} of the full-horizon "
                        f"MS optimum after agent {total}")
            return (f"estimated {name} improvement still to come {self.remaining:.2e}{unit} "
                    f"after agent {total}{self._certificate_failure}")
        if total >= settings.max_agents:
            self._try_certificate("budget", agent, solve)
            self._measure()
            return (f"max_agents {settings.max_agents} reached; the train's "
                    f"{self.remaining_method} {name} improvement still to come "
                    f"{self.remaining:.2e}{unit}{self._certificate_failure}")
        if self.certificate is not None and self.remaining > STALL_RATIO * self.estimate:
            self.stalled = True
            return (f"stalled after agent {total} with windows N_Δ = {settings.window}, "
                    f"N_δ = {settings.update}: {self.remaining:.2e}{unit} short of the "
                    f"full-horizon MS optimum, its gains estimated to close "
                    f"{self.estimate:.2e}{unit}")
        return None

    def _measure(self) -> None:
        """:attr:`remaining`: the distance of the last finished agent's headline to the
        certificate's (0 once it passes it), or the extrapolated estimate without one."""
        if self.certificate is None:
            self.remaining, self.remaining_method = self.estimate, REMAINING_METHODS[0]
        else:
            to_come = self.problem.improvement(self.headlines[-1], self.certificate.headline)
            self.remaining, self.remaining_method = max(0.0, to_come), REMAINING_METHODS[1]

    def _try_certificate(self, trigger: str, agent: Agent,
                         solve: Callable[[OcpTask], MsSolution]) -> None:
        """:meth:`certify` from ``agent`` once per ``trigger``, unless the train has a
        certificate or the horizon does not fit."""
        if self.certificate is None and self._fits and trigger not in self._tried:
            self._tried.add(trigger)
            self.certify(agent, solve)

    def certify(self, agent: Agent, solve: Callable[[OcpTask], MsSolution]) -> None:
        """Solve the full-horizon MS problem from ``agent``'s trajectory (agent 0's if that
        fails) with ``solve``; accepted as :attr:`certificate` if it succeeds and its
        trajectory, as returned, meets the dynamics, the target set and the path constraints
        to :data:`FEASIBILITY_TOL` (:func:`~ocpar.pursuit.validate.discrete_residual`). A
        failure is noted and leaves the extrapolated estimate in charge."""
        sol = solve(full_horizon_task(self.problem, agent.x, agent.u,
                                      fallback=(self.initial.x, self.initial.u),
                                      options=self.settings.solver_options))
        self.solves += 1
        self.retries += sol.attempts - 1
        total = self.agents_before + agent.index
        status = sol.status
        if sol.success:
            residual = discrete_residual(self.problem, sol.x, sol.u)
            if residual <= FEASIBILITY_TOL:
                self.certificate = Certificate(total, self.problem.headline_value(sol.x, sol.u),
                                               sol.x, sol.u)
                self._certificate_failure = ""
                return
            status = f"its trajectory breaks the constraints by {residual:.2e}"
        self.failed += 1
        self.failures.append(f"full-horizon certificate after agent {total}: {status}")
        self._certificate_failure = f" (the full-horizon certificate failed: {status})"


def widen(settings: PursuitSettings, samples: int) -> PursuitSettings | None:
    """``settings`` with windows spanning twice the time, as a level twice as coarse has:
    N_Δ → 2N_Δ − 1 and N_δ → 2N_δ, at most N − 1 and N_Δ − 1; None if N_Δ is N − 1 already."""
    if settings.window >= samples - 1:
        return None
    window = min(2 * settings.window - 1, samples - 1)
    return dataclasses.replace(settings, window=window,
                               update=min(2 * settings.update, window - 1))


def run_pursuit(
    problem: PursuitProblem,
    settings: PursuitSettings,
    backend: Backend,
    progress: Callable[[str], None] | None = None,
) -> PursuitOutcome:
    """Run PBMS until the stopping test; one superstep per wave of ready updates. A train
    that stalls (:data:`STALL_RATIO`) starts again from its last agent with windows twice as
    long (:func:`widen`), keeping its certificate and agent count; the answer is the train's
    last agent or the certificate, whichever is better (:func:`conclude`)."""
    trains: list[PursuitTrain] = []
    stage_problem, stage_settings = problem, settings
    max_in_flight, certificate, agents = 0, None, 0
    while True:
        train = PursuitTrain(stage_problem, stage_settings, certificate, agents)
        trains.append(train)
        while True:
            work = train.ready()
            if not work:
                raise RuntimeError("pursuit schedule stalled: no agent can move")  # a bug if seen
            max_in_flight = max(max_in_flight, len(work))
            # cost estimate: a subproblem's size, its number of intervals (free-running ones
            # are shorter); longest-first keeps the two or three catch-ups of a wave on
            # different workers
            sols = backend.superstep(solve_tasks, [task for _, task in work],
                                     costs=[task.shape.intervals for _, task in work])
            for (agent, _), sol in zip(work, sols, strict=True):
                train.apply(agent, sol)
            trace = backend.traces[-1]  # the wave's, not the certificate's
            note = train.retire_finished(
                lambda task: backend.superstep(solve_task, [task])[0])
            if progress is not None:
                progress(
                    f"superstep {trace.index:5d}  agents in flight {len(work):3d}  "
                    f"finished {agents + len(train.headlines) - 1:5d}  last "
                    f"{problem.headline_name} {train.headlines[-1]:.6f} "
                    f"{problem.headline_unit}  wall {trace.wall_s * 1e3:6.1f} ms"
                )
            if note is not None:
                break
        agents += train.best.index
        certificate = train.certificate
        wider = widen(stage_settings, problem.samples) if train.stalled else None
        if wider is None:
            return conclude(problem, settings, trains, note, max_in_flight)
        if progress is not None:
            progress(f"{note}; windows widened to N_Δ = {wider.window}, N_δ = {wider.update}")
        x, u = train.best.x, train.best.u
        stage_problem = dataclasses.replace(problem, plan=SampledPlan(
            np.clip(x, *problem.model.state_bounds()), np.clip(u, *control_bounds(problem.model))))
        stage_settings = wider


def conclude(problem: PursuitProblem, settings: PursuitSettings, trains: list[PursuitTrain],
             note: str, max_in_flight: int) -> PursuitOutcome:
    """The outcome of the ``trains`` of one run (a stalled train, then each widened one;
    ``note`` the last one's stop): the certificate if it is at least as good as the last
    agent, else the last agent, and whether that answer is converged: within ε of the
    certificate's optimum (an estimate below ε without a certificate stops the run, and says
    so, but is not convergence)."""
    train, eps = trains[-1], settings.epsilon
    unit = f" {problem.headline_unit}".rstrip()
    certificate, best = train.certificate, train.best
    train_headline = train.headlines[-1]
    if certificate is not None and problem.improvement(train_headline,
                                                       certificate.headline) >= 0:
        source, x, u, remaining = RESULT_SOURCES[1], certificate.x, certificate.u, 0.0
        answer = (f"; returned: the full-horizon MS solved from agent {certificate.agent}'s "
                  f"trajectory, {problem.headline_name} {certificate.headline:.6f}{unit}")
    else:
        source, x, u, remaining = RESULT_SOURCES[0], best.x, best.u, train.remaining
        answer = ""
    if certificate is not None and remaining < eps:
        stop_reason, method = STOP_REASONS[0], REMAINING_METHODS[1]
    elif certificate is None and remaining < eps:
        stop_reason, method = STOP_REASONS[1], REMAINING_METHODS[0]
    else:
        stop_reason, method = STOP_REASONS[2], train.remaining_method
    headlines = train.headlines
    if len(trains) > 1:
        headlines = trains[0].headlines + [h for t in trains[1:] for h in t.headlines[1:]]
    return PursuitOutcome(
        best=best, x=x, u=u, result_source=source, headlines=headlines,
        train_headline=train_headline, train_remaining=train.remaining,
        train_remaining_method=train.remaining_method,
        subproblem_solves=sum(t.solves for t in trains),
        failed_solves=sum(t.failed for t in trains),
        retries=sum(t.retries for t in trains),
        max_in_flight=max_in_flight, converged=certificate is not None and remaining < eps,
        message=note + answer + ("" if certificate is not None or remaining >= eps else
                                 "; not converged: within ε by the train's extrapolated "
                                 "estimate only, without a full-horizon certificate"),
        stop_reason=stop_reason, remaining=remaining,
        remaining_method=method, certificate=certificate,
        failures=[f for t in trains for f in t.failures][:20],
        agents_per_level=[train.agents_before + best.index],
        windows=[(t.settings.window, t.settings.update) for t in trains])


def run_levels(
    problem: PursuitProblem,
    settings: PursuitSettings,
    backend: Backend,
    progress: Callable[[str], None] | None = None,
) -> PursuitOutcome:
    """PBMS coarse to fine (``settings.levels`` L > 1): :func:`run_pursuit` on
    (N−1)/2^(L−1)+1 samples from the problem's agent 0, then on each grid twice as fine with
    the same N_Δ, N_δ (so a coarse level's windows span more time, and its train converges in
    fewer agents) and the coarser level's answer as agent 0 (:func:`refine`). The outcome is
    the finest level's (its headlines, stop reason), with the solves and agents of all
    levels. L = 1 is :func:`run_pursuit`."""
    levels: list[PursuitOutcome] = []
    one_level = dataclasses.replace(settings, levels=1)
    for level in range(settings.levels - 1, -1, -1):
        samples = (problem.samples - 1) // 2**level + 1
        if not levels:
            grid = coarsen(problem, samples)
        else:
            # within the bounds, which a subproblem's solution may overstep by its tolerance
            x, u = refine(levels[-1].x, levels[-1].u)
            x = np.clip(x, *problem.model.state_bounds())
            grid = dataclasses.replace(problem, samples=samples, plan=SampledPlan(
                x, np.clip(u, *control_bounds(problem.model))))
        levels.append(run_pursuit(grid, one_level, backend, progress))
    last = levels[-1]
    return dataclasses.replace(
        last, subproblem_solves=sum(o.subproblem_solves for o in levels),
        failed_solves=sum(o.failed_solves for o in levels),
        retries=sum(o.retries for o in levels),
        max_in_flight=max(o.max_in_flight for o in levels),
        failures=[f for o in levels for f in o.failures][:20],
        agents_per_level=[o.agents_per_level[0] for o in levels])


def coarsen(problem: PursuitProblem, samples: int) -> PursuitProblem:
    """``problem`` on ``samples`` samples, (N−1)/(samples−1) an integer: a control law is
    integrated on the coarse grid, a sampled plan subsampled (each coarse interval holds the
    control of its first fine interval)."""
    if samples == problem.samples:
        return problem
    step = (problem.samples - 1) // (samples - 1)
    plan = problem.plan
    if isinstance(plan, SampledPlan):
        plan = SampledPlan(plan.states[::step], plan.controls[::step])
    return dataclasses.replace(problem, samples=samples, plan=plan)


def refine(x: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A trajectory on a grid twice as fine: states (N, nx) -> (2N−1, nx), the new samples
    midway between their neighbours; controls (N−1, nu) -> (2N−2, nu), each held twice."""
    fine = np.empty((2 * len(x) - 1, x.shape[1]))
    fine[::2], fine[1::2] = x, (x[:-1] + x[1:]) / 2
    return fine, np.repeat(u, 2, axis=0)
