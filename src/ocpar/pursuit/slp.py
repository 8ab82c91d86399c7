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

The train stops when the headline's improvement still to come, estimated from the agents'
recent gains (:func:`remaining_improvement`), is below ε, or after ``max_agents`` agents.
With ``levels`` L > 1 the train runs first on a grid 2^(L−1) times coarser, then on grids
twice as fine, each from the coarser result (:func:`run_levels`).

All agents whose next update has what it needs (from earlier supersteps) solve in one
superstep, so about (N−1)/(N_Δ−1) agents run in parallel. The computation is the SLP of the
paper whatever the schedule: each update depends only on data fixed by the rules, so results
do not depend on the backend or the worker count.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from ocpar.bsp import Backend
from ocpar.models.ode import control_bounds
from ocpar.ocp import MsShape, MsSolution, OcpTask, solve_tasks
from ocpar.ocp.multiple_shooting import LOCAL_SOLVERS
from ocpar.options import option
from ocpar.pursuit.problem import PursuitProblem, SampledPlan


@dataclass(frozen=True)
class PursuitSettings:
    """SLP settings: ``window`` N_Δ (samples per catch-up problem), ``update`` N_δ (samples
    applied per update), ``epsilon`` the stopping threshold on the estimated improvement of
    the problem's headline still to come (in the headline's unit; see
    :func:`remaining_improvement`), ``max_agents`` a bound on the number of pursuing agents
    (per level), ``levels`` the coarse-to-fine levels (:func:`run_levels`; 1: the paper's
    scheme), ``local_solver`` the subproblems' solver from the leader's plan (IPOPT if it fails; see
    :class:`~ocpar.ocp.MsShape`)."""

    window: int = option(60, "samples per catch-up problem N_Δ (Δ = (N_Δ-1)h)", low=2,
                         metavar="N_DELTA")
    update: int = option(32, "samples applied per update N_δ (δ = N_δ h)", low=1,
                         metavar="N_UPDATE")
    epsilon: float = option(1e-3, "stop when the improvement of the headline still to come, "
                            "estimated from the agents' recent rate, is below EPS (in the "
                            "headline's unit, kg for the orbit transfer)",
                            above=0, metavar="EPS")
    max_agents: int = option(100_000, "stop after this many agents", low=2)
    levels: int = option(1, "coarse-to-fine levels L: PBMS first on (N-1)/2^(L-1)+1 samples, "
                         "then on grids twice as fine, each starting from the coarser result "
                         "(agent 0); 1: the paper's scheme", low=1)
    local_solver: str = option("newton", "subproblems' solver from the leader's plan: newton "
                               "(Newton steps on the KKT system) or sqp (CasADi sqpmethod, "
                               "qrqp); IPOPT if it fails", choices=LOCAL_SOLVERS)

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


#: Fewest agent-to-agent improvements :func:`remaining_improvement` estimates from.
MIN_GAINS = 8
#: Why a run stopped (``result.json``'s ``stop_reason``).
STOP_REASONS = ("remaining_below_epsilon", "max_agents")


def remaining_improvement(progress: Sequence[float]) -> float:
    """The improvement still to come, estimated from the recent rate. ``progress[i]`` is how
    much agent i + 1 improves on agent 1 (0 first; non-decreasing by Theorem 1), so its k
    increments are the successive agents' gains. The gains of the last quarter of the agents,
    S = progress[k] − progress[k − w] (w = k // 4), and of the quarter before, S', are
    continued as a geometric series: S ρ/(1 − ρ) with ρ = S/S'.

    Exact when the gains decay geometrically; an underestimate when they decay more slowly
    (the diffusion-like descent of a long horizon: compare the headline with a reference
    before trusting it there); ``inf`` while the gains do not shrink (ρ ≥ 1) or with fewer
    than :data:`MIN_GAINS` gains; 0 when the last quarter brought no improvement.
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


@dataclass
class PursuitOutcome:
    """What the pursuit loop returns: the last finished agent (the result), every finished
    agent's headline (agent 0 first), counters and status: why it stopped (one of
    :data:`STOP_REASONS`) and the estimated improvement still to come (``remaining``, in the
    headline's unit; :func:`remaining_improvement`)."""

    best: Agent
    initial: Agent
    headlines: list[float]
    subproblem_solves: int
    failed_solves: int
    retries: int
    max_in_flight: int
    converged: bool
    message: str
    stop_reason: str
    remaining: float
    failures: list[str] = field(default_factory=list)
    #: agents of each level, coarsest first (:func:`run_levels`)
    agents_per_level: list[int] = field(default_factory=list)


class PursuitTrain:
    """The coordinator's state: agents in flight, each one's leader, the finished agents'
    headlines."""

    def __init__(self, problem: PursuitProblem, settings: PursuitSettings) -> None:
        settings.check(problem.samples)
        #: Fewest intervals a problem to the target set needs: as many controls as fixed
        #: components (⌈|S| / nu⌉).
        self.min_intervals = -(-len(problem.target_components) // problem.model.nu)
        self.problem, self.settings = problem, settings
        n = problem.samples
        x0, u0 = problem.feasible_trajectory()
        self.initial = Agent(0, x0, u0, position=n - 1)
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
        #: the estimated improvement still to come (:func:`remaining_improvement`)
        self.remaining = float("inf")

    def _shape(self, intervals: int) -> MsShape:
        """The subproblem shape with ``intervals`` intervals (made once per train)."""
        shape = self._shapes.get(intervals)
        if shape is None:
            problem = self.problem
            shape = self._shapes[intervals] = MsShape(
                problem.model, intervals, problem.step, problem.target_components,
                problem.integrator, warm_start=True, local_solver=self.settings.local_solver,
                path_constraints=problem.path_constraints)
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
        if self.launched < self.settings.max_agents and last.position >= window - 1:
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

    def retire_finished(self) -> tuple[bool, str, str] | None:
        """Take finished agents off the train in order; return (converged, stop reason,
        message) when the estimated improvement still to come (:attr:`remaining`) falls below
        ε or the agent budget is spent, else None."""
        while self.in_flight and self.in_flight[0].done:
            agent = self.in_flight.pop(0)
            self.headlines.append(self.problem.headline_value(agent.x, agent.u))
            self.leaders.pop(agent.index, None)
            self.best = agent
            if agent.index >= 1:  # agent 0 does not end on S_Q: progress from agent 1 on
                self.progress.append(self.problem.improvement(self.headlines[1],
                                                              self.headlines[-1]))
                self.remaining = remaining_improvement(self.progress)
            unit = f" {self.problem.headline_unit}".rstrip()
            if self.remaining < self.settings.epsilon:
                return True, STOP_REASONS[0], (
                    f"estimated {self.problem.headline_name} improvement still to come "
                    f"{self.remaining:.2e}{unit} < epsilon {self.settings.epsilon:g}{unit} "
                    f"after agent {agent.index}")
            if agent.index >= self.settings.max_agents:
                return False, STOP_REASONS[1], (
                    f"max_agents {self.settings.max_agents} reached; estimated "
                    f"{self.problem.headline_name} improvement still to come "
                    f"{self.remaining:.2e}{unit}")
        return None


def run_pursuit(
    problem: PursuitProblem,
    settings: PursuitSettings,
    backend: Backend,
    progress: Callable[[str], None] | None = None,
) -> PursuitOutcome:
    """Run PBMS until the stopping test; one superstep per wave of ready updates."""
    train = PursuitTrain(problem, settings)
    max_in_flight = 0
    while True:
        work = train.ready()
        if not work:
            raise RuntimeError("pursuit schedule stalled: no agent can move")  # a bug if seen
        max_in_flight = max(max_in_flight, len(work))
        # cost estimate: a subproblem's size, its number of intervals (free-running ones are
        # shorter); longest-first keeps the two or three catch-ups of a wave on different workers
        sols = backend.superstep(solve_tasks, [task for _, task in work],
                                 costs=[task.shape.intervals for _, task in work])
        for (agent, _), sol in zip(work, sols, strict=True):
            train.apply(agent, sol)
        verdict = train.retire_finished()
        if progress is not None:
            trace = backend.traces[-1]
            progress(
                f"superstep {trace.index:5d}  agents in flight {len(work):3d}  "
                f"finished {len(train.headlines) - 1:5d}  last {problem.headline_name} "
                f"{train.headlines[-1]:.6f} {problem.headline_unit}  "
                f"wall {trace.wall_s * 1e3:6.1f} ms"
            )
        if verdict is not None:
            converged, stop_reason, message = verdict
            return PursuitOutcome(
                best=train.best,
                initial=train.initial,
                headlines=train.headlines,
                subproblem_solves=train.solves,
                failed_solves=train.failed,
                retries=train.retries,
                max_in_flight=max_in_flight,
                converged=converged,
                message=message,
                stop_reason=stop_reason,
                remaining=train.remaining,
                failures=train.failures[:20],
                agents_per_level=[train.best.index],
            )


def run_levels(
    problem: PursuitProblem,
    settings: PursuitSettings,
    backend: Backend,
    progress: Callable[[str], None] | None = None,
) -> PursuitOutcome:
    """PBMS coarse to fine (``settings.levels`` L > 1): :func:`run_pursuit` on
    (N−1)/2^(L−1)+1 samples from the problem's agent 0, then on each grid twice as fine with
    the same N_Δ, N_δ (so a coarse level's windows span more time, and its train converges in
    fewer agents) and the coarser level's result as agent 0 (:func:`refine`). The outcome is
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
            x, u = refine(levels[-1].best.x, levels[-1].best.u)
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
        agents_per_level=[o.best.index for o in levels])


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
