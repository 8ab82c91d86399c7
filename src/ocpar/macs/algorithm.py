"""MACSoc (Algorithm 1): a population of agents, individualistic and social actions, a Pareto
archive with a potential-field filter, and subproblem allocation.

Each iteration is two supersteps: every agent's individualistic action (a Pascoletti–Serafini
local search, Algorithm 2) in one, every agent's social action (a differential-evolution
candidate followed by constraint restoration, Algorithms 3–4) in the other. All random draws
come from per-agent generators seeded from (seed, agent), in agent order on the coordinator,
so results do not depend on the backend or the worker count.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from itertools import pairwise
from typing import Any

import numpy as np
from scipy.stats import qmc

from ocpar.bsp import Backend
from ocpar.macs.archive import Archive, Member, dominates
from ocpar.macs.local_search import (
    RESTORATIONS,
    STATIONARITY_TOL,
    SearchResult,
    SearchTask,
    run_search,
)
from ocpar.macs.metrics import arc_lengths
from ocpar.macs.problem import MacsProblem
from ocpar.ocp import dfet_problem
from ocpar.ocp.solver_options import SOLVER_OPTIONS_HELP, solver_options
from ocpar.options import option

#: Most agents: each runs one local search per superstep (the paper used 10).
MAX_POPULATION = 10_000
#: Most rounds (supersteps) of the final refinement's checks: a round after the first
#: re-checks only the members that a neighbour's start moved, or whose neighbours it moved.
REFINEMENT_ROUNDS = 12
#: The rounds after the first together spend at most this multiple of the first round's
#: evaluations: no round starts once they have (its members that moved stay unsettled).
REFINEMENT_BUDGET = 2.0


def front_neighbours(objectives: np.ndarray) -> list[list[int]]:
    """Each member's neighbours on the front, from the members' objectives (k, m): the members
    just before and just after it in the order of each objective (with two objectives, the
    members on either side of it along the front), as ascending indices."""
    neighbours: list[set[int]] = [set() for _ in range(len(objectives))]
    for column in np.asarray(objectives).T:
        order = np.argsort(column, kind="stable")
        for a, b in pairwise(order):
            neighbours[a].add(int(b))
            neighbours[b].add(int(a))
    return [sorted(n) for n in neighbours]


def subproblem_weights(m: int) -> list[np.ndarray]:
    """The paper's Tchebycheff weights λ (§IV-B) for m objectives: subproblem i < m minimises
    objective i (λ = e_i), subproblem m the equal-weight direction (1, …, 1)/√m."""
    return [*np.eye(m), np.full(m, 1 / np.sqrt(m))]


@dataclass(frozen=True)
class MacsSettings:
    """Table I of the paper: ``max_evaluations`` (max_fun_eval), ``population`` (pop_size),
    ``rho_initial`` (ρ_ini, as a fraction of each decision variable's range), ``de_weight``
    (F), ``crossover`` (CR), ``social_fraction`` (p_social), ``archive_size`` (max_arch),
    ``max_contractions`` (max_contr_ratio); ``contraction`` is the factor applied to ρ on a
    failed local search, ``seed`` the master seed, ``restoration`` how a restoration's IPOPT
    stops (:data:`~ocpar.macs.local_search.RESTORATIONS`), ``no_refine`` skips the final
    refinement of the archive (:meth:`Macs.refine`), ``no_spread`` the final placement
    before it (:meth:`Macs.spread`), ``solver_options`` IPOPT's own options
    of every local search by ``ipopt.NAME`` (:mod:`ocpar.ocp.solver_options`; the searches
    are IPOPT's alone), checked when the settings are made."""

    max_evaluations: int = option(
        10_000, "budget of objective evaluations (> --population), checked before each "
        "iteration: the last iteration begun ends past it; the final placement and "
        "refinement add theirs", name="max_evals", low=1,
        metavar="N")
    population: int = option(10, "number of agents pop_size", low=4, high=MAX_POPULATION)
    archive_size: int = option(20, "archive size max_arch, at least 2 (the paper used 10)",
                               name="archive")
    rho_initial: float = option(1.0, "initial radius ρ_ini, a fraction of each variable's "
                                "range, in (0, 1]", above=0, high=1)
    de_weight: float = option(0.9, "differential evolution weight F, in (0, 2]", above=0,
                              high=2)
    crossover: float = option(0.9, "crossover probability CR, in [0, 1]", low=0, high=1)
    social_fraction: float = option(1.0, "fraction of agents doing social moves p_social",
                                    low=0, high=1)
    max_contractions: int = option(5, "contractions of ρ before an agent restarts", low=0)
    contraction: float = option(0.5, "factor applied to ρ on a failed local search, in (0, 1)",
                                above=0, high=1)
    seed: int = option(0, "master seed of the random draws", low=0)
    restoration: str = option(
        "centred", "how a restoration stops: centred (IPOPT to tol 1e-8, the point centred "
        "between its bounds) or feasible (at the first feasible point: about half the "
        "restorations' time, but restored points nearer the front may stay unpolished in the "
        "archive)", choices=RESTORATIONS)
    no_refine: bool = option(False, "skip the final refinement (every archive member re-solved "
                             "once by an ε-constraint NLP, with its Pareto-stationarity "
                             "residual)")
    no_spread: bool = option(False, "skip the final placement (members re-solved at targets "
                             "equally spaced in arc length along the front, two objectives)")
    solver_options: dict = option(  # noqa: RUF009 (option() is a dataclass field)
        default_factory=dict, help=SOLVER_OPTIONS_HELP + "; MACS's local searches are "
        "IPOPT's: ipopt.* only", flag="--solver-option", metavar="SOLVER.NAME=VALUE",
        dotted=True)

    def __post_init__(self) -> None:
        checked = solver_options(self.solver_options)
        if others := [key for key, _ in checked if not key.startswith("ipopt.")]:
            raise ValueError(f"solver option {others[0]}: MACS's local searches are solved "
                             "by IPOPT alone (ipopt.* options only)")
        object.__setattr__(self, "solver_options", dict(checked))
        checks = [
            (self.max_evaluations >= 1, "max_evaluations must be >= 1"),
            (self.population >= 4, "population must be >= 4 (differential evolution)"),
            (self.archive_size >= 2, "archive_size must be >= 2"),
            (0 < self.rho_initial <= 1, "rho_initial must be in (0, 1]"),
            (0 < self.de_weight <= 2, "de_weight F must be in (0, 2]"),
            (0 <= self.crossover <= 1, "crossover CR must be in [0, 1]"),
            (0 <= self.social_fraction <= 1, "social_fraction must be in [0, 1]"),
            (self.max_contractions >= 0, "max_contractions must be >= 0"),
            (0 < self.contraction < 1, "contraction must be in (0, 1)"),
            (self.seed >= 0, "seed must be >= 0"),
            (self.restoration in RESTORATIONS,
             f"restoration must be one of {', '.join(RESTORATIONS)}"),
        ]
        for ok, message in checks:
            if not ok:
                raise ValueError(message)


def task_kind(task: SearchTask) -> str:
    """What a task's time depends on most: its kind, and for a search whether it starts from
    a full NLP vector or integrates its states from a decision vector first."""
    return task.kind if task.kind == "restore" else f"{task.kind}-{'z' if task.p0 is None else 'p'}"


@dataclass
class TaskCosts:
    """Running mean of the measured time (s) of each kind of task (:func:`task_kind`): the
    cost estimates by which a superstep's searches go to workers longest-first. A kind not
    yet measured gets the mean of all tasks measured so far (all tasks equal at first)."""

    total: dict[str, float] = field(default_factory=dict)
    count: dict[str, int] = field(default_factory=dict)

    def estimate(self, kinds: list[str]) -> list[float]:
        n = sum(self.count.values())
        default = sum(self.total.values()) / n if n else 1.0
        return [self.total[k] / self.count[k] if k in self.count else default for k in kinds]

    def update(self, kinds: list[str], seconds: list[float]) -> None:
        for kind, s in zip(kinds, seconds, strict=True):
            self.total[kind] = self.total.get(kind, 0.0) + s
            self.count[kind] = self.count.get(kind, 0) + 1


@dataclass
class Agent:
    """One MACS agent: its point (``z``, ``objectives``; None before its first feasible
    point), neighbourhood radius ``rho``, subproblem, and random generator."""

    index: int
    rng: np.random.Generator
    subproblem: int
    rho: float
    decision: np.ndarray
    z: np.ndarray | None = None
    objectives: np.ndarray | None = None
    contractions: int = 0
    fresh: bool = True
    moved: bool = False


@dataclass
class MacsOutcome:
    """Archive, counters and per-iteration history of a MACS run; ``fronts`` the archive's
    objectives (k, m) after every iteration; ``refinement_evaluations`` those of the final
    refinement (included in ``evaluations``)."""

    archive: Archive
    evaluations: int
    iterations: int
    failed_searches: int
    history: list[dict] = field(default_factory=list)
    fronts: list[np.ndarray] = field(default_factory=list)
    refinement_evaluations: int = 0
    #: the first failed search's IPOPT status ('' if none failed)
    first_failure: str = ""
    #: the refinement's rounds of checks, and the evaluations of those after the first
    refinement_rounds: int = 0
    refinement_extra_evaluations: int = 0
    #: the final placement's evaluations and targets reached (:meth:`Macs.spread`)
    spread_evaluations: int = 0
    spread_placed: int = 0


class Macs:
    """The MACSoc coordinator for one problem on one backend."""

    def __init__(
        self,
        problem: MacsProblem,
        settings: MacsSettings,
        backend: Backend,
        progress: Callable[[str], None] | None = None,
        indicator: Callable[[np.ndarray], float] | None = None,
    ) -> None:
        self.problem, self.settings, self.backend = problem, settings, backend
        self.solver_options = solver_options(settings.solver_options)
        self.progress, self.indicator = progress, indicator
        dfet = dfet_problem(problem.shape)
        self.lower, self.upper = dfet.p_lower, dfet.p_upper
        self.decision_slice = dfet.decision_slice
        self.m = problem.n_objectives
        self.weights = subproblem_weights(self.m)
        self.equal = self.m  # the equal-weight subproblem
        self.archive = Archive(settings.archive_size, self.m)
        self.evaluations = 0
        self.failed = 0
        self.first_failure = ""
        self.costs = TaskCosts()
        #: the final refinement's rounds and the evaluations of those after the first
        self.rounds = self.extra_evaluations = 0
        #: the final placement's targets reached (:meth:`spread`)
        self.placed = 0
        seeds = np.random.SeedSequence(settings.seed).spawn(settings.population + 1)
        sample = qmc.LatinHypercube(d=len(self.lower), seed=np.random.default_rng(seeds[-1]))
        # scaled by hand: qmc.scale refuses a fixed t_f (lower == upper)
        starts = sample.random(settings.population) * (self.upper - self.lower) + self.lower
        self.agents = [
            Agent(j, np.random.default_rng(seeds[j]), j if j < self.m else self.equal,
                  settings.rho_initial, starts[j])
            for j in range(settings.population)
        ]

    # -- supersteps -------------------------------------------------------------------------
    def _task(self, kind: str, **fields: Any) -> SearchTask:
        """A task of ``kind`` on this run's problem, with its solver options."""
        return SearchTask(self.problem, kind, solver_options=self.solver_options, **fields)

    def _superstep(self, tasks: list[SearchTask]) -> list[SearchResult]:
        kinds = [task_kind(task) for task in tasks]
        results = self.backend.superstep(run_search, tasks, costs=self.costs.estimate(kinds))
        self.costs.update(kinds, self.backend.traces[-1].task_wall_s)
        self.evaluations += sum(r.evaluations for r in results)
        self.failed += sum(not r.feasible for r in results)
        if not self.first_failure:
            self.first_failure = next((r.status for r in results if not r.feasible), "")
        return results

    def _archive(self, results: list[SearchResult], optimised: bool) -> None:
        self.archive.add([Member(r.z, r.objectives, optimised) for r in results if r.feasible])

    def _span(self) -> np.ndarray:
        """z*_A − z of the (non-empty) archive (m,), at least 1e-3 max(|z|, 1) when flat."""
        ideal, nadir = self.archive.ideal_and_nadir()
        return np.maximum(nadir - ideal, 1e-3 * np.maximum(np.abs(ideal), 1.0))

    def _utopia(self) -> np.ndarray:
        """z̃ = 2z − z*_A from the archive (eq. 15), pushed away when the archive is flat."""
        return self.archive.ideal_and_nadir()[0] - self._span()

    def _neighbour(self, agent: Agent) -> np.ndarray:
        """A random decision vector in agent's neighbourhood B_j (radius ρ_j of the range)."""
        step = agent.rho * (self.upper - self.lower) * agent.rng.uniform(-1, 1, len(self.lower))
        return np.clip(agent.decision + step, self.lower, self.upper)

    def initialise(self) -> None:
        """Restore feasibility of the Latin-hypercube population; seed the archive."""
        tasks = [self._task("restore", p0=a.decision, restoration=self.settings.restoration)
                 for a in self.agents]
        results = self._superstep(tasks)
        for agent, result in zip(self.agents, results, strict=True):
            if result.feasible:
                self._move(agent, result)
        self._archive(results, optimised=False)

    def individualistic(self) -> None:
        """Algorithm 2 for every agent: a scalarised local search from the agent's point if it
        moved since its last one; otherwise from an archive member that only restoration has
        produced (it gets polished onto the front: our addition), or else from a random point
        of the agent's neighbourhood B_j. ρ_j contracts when the search does not move the
        agent (infeasible or no better) and resets after ``max_contractions``."""
        utopia = self._utopia()
        unpolished = [m for m in self.archive.members if not m.optimised]
        tasks = []
        for agent in self.agents:
            weights = self.weights[agent.subproblem]
            if agent.fresh and agent.z is not None:
                task = self._task("scalarised", z0=agent.z, weights=weights, utopia=utopia)
            elif unpolished:
                member = unpolished.pop(0)
                member.optimised = True  # claimed: polished by this search
                task = self._task("scalarised", z0=member.z,
                                  weights=self.weights[self.equal], utopia=utopia)
            else:
                task = self._task("scalarised", p0=self._neighbour(agent), weights=weights,
                                  utopia=utopia)
            tasks.append(task)
        results = self._superstep(tasks)
        scale = self._scale()
        for agent, result in zip(self.agents, results, strict=True):
            agent.fresh = False
            moved = result.feasible and self._improves(agent, result, scale)
            if moved:
                self._move(agent, result)
            elif agent.contractions >= self.settings.max_contractions:
                agent.rho, agent.contractions = self.settings.rho_initial, 0
            else:
                agent.rho *= self.settings.contraction
                agent.contractions += 1
        self._archive(results, optimised=True)

    def _scale(self) -> tuple[np.ndarray, np.ndarray]:
        """(z, z*_A − z) of the (non-empty) archive: the Tchebycheff value's origin and scale,
        computed once for all agents of a superstep (the archive changes only after them)."""
        ideal, nadir = self.archive.ideal_and_nadir()
        return ideal, np.maximum(nadir - ideal, 1e-12)

    def _tchebycheff(self, agent: Agent, objectives: np.ndarray,
                     scale: tuple[np.ndarray, np.ndarray]) -> float:
        """max_i λ_i |J_i − z_i| / (z*_A,i − z_i): the agent's scalar figure of merit."""
        ideal, span = scale
        return float(np.max(self.weights[agent.subproblem] * np.abs(objectives - ideal) / span))

    def _improves(self, agent: Agent, result: SearchResult,
                  scale: tuple[np.ndarray, np.ndarray]) -> bool:
        """The result is better for the agent: it dominates the agent's point or has a lower
        Tchebycheff value (on the archive's ``scale``, :meth:`_scale`)."""
        if agent.objectives is None or dominates(result.objectives, agent.objectives):
            return True
        return self._tchebycheff(agent, result.objectives, scale) < self._tchebycheff(
            agent, agent.objectives, scale)

    def social(self) -> None:
        """Algorithms 3–4: a DE/rand/1/bin candidate from agents of the same subproblem and
        archive members, made feasible by restoration; kept if it improves the agent's
        Tchebycheff value."""
        social = [a for a in self.agents
                  if a.rng.random() < self.settings.social_fraction]
        if not social:
            return
        archive_points = [m.z[self.decision_slice] for m in self.archive.members]
        tasks = []
        for agent in social:
            pool = [a.decision for a in self.agents
                    if a.subproblem == agent.subproblem and a is not agent] + archive_points
            if len(pool) < 3:
                pool += [a.decision for a in self.agents if a is not agent]
            r1, r2, r3 = agent.rng.choice(len(pool), 3, replace=False)
            mutant = pool[r1] + self.settings.de_weight * (pool[r2] - pool[r3])
            mask = agent.rng.random(len(mutant)) < self.settings.crossover
            mask[agent.rng.integers(len(mutant))] = True
            candidate = np.clip(np.where(mask, mutant, agent.decision), self.lower, self.upper)
            tasks.append(self._task("restore", p0=candidate,
                                    restoration=self.settings.restoration))
        results = self._superstep(tasks)
        scale = self._scale()
        for agent, result in zip(social, results, strict=True):
            if result.feasible and self._improves(agent, result, scale):
                self._move(agent, result)
        self._archive(results, optimised=False)

    def reallocate(self) -> None:
        """Line 10: an agent that did not move this iteration switches between a
        single-objective subproblem (drawn at random) and the equal-weight direction."""
        for agent in self.agents:
            if not agent.moved:
                agent.subproblem = (int(agent.rng.integers(self.m))
                                    if agent.subproblem == self.equal else self.equal)
            agent.moved = False

    def spread(self) -> int:
        """The final filter's placement (two objectives): ``archive_size`` targets equally
        spaced in arc length along the polyline through the members sorted by J1, in
        objectives normalised to the archive's span (:func:`~ocpar.macs.metrics.arc_lengths`;
        its two ends the extreme members, kept). Each inner target is reached in one
        superstep by the ε-constraint NLP min J_m s.t. J_1 ≤ the target's J_1, from the two
        members around it along the front; the lower J_m of the kept solves (feasible, within
        ε) becomes a member, and a target neither start reaches keeps the member nearest
        to it. The members are then only these (dominated or repeated ones dropped); the
        refinement (:meth:`refine`) checks them next. ``placed`` counts the targets reached.
        Returns the evaluations."""
        members = sorted(self.archive.members, key=lambda member: member.objectives[0])
        self.placed = 0
        if self.m != 2 or len(members) < 2:
            return 0
        before = self.evaluations
        ideal, span = self.archive.ideal_and_nadir()[0], self._span()
        normalised = (np.array([mb.objectives for mb in members]) - ideal) / span
        lengths = arc_lengths(normalised)
        along = np.linspace(0.0, lengths[-1], self.settings.archive_size)[1:-1]
        bounds = ideal[0] + span[0] * np.interp(along, lengths, normalised[:, 0])
        # the members around each target along the front: the last at or before it, the next
        after = np.clip(np.searchsorted(lengths, along, side="right"), 1, len(members) - 1)
        ceiling = ideal[-1] + 2 * span[-1]  # any J_m: only J_1 is bounded
        tasks = [self._task("refine", z0=members[j].z, span=span,
                            epsilon=np.array([bound, ceiling]))
                 for bound, k in zip(bounds, after, strict=True) for j in (k - 1, k)]
        results = self._superstep(tasks)
        placed = [members[0]]
        for n, (position, k) in enumerate(zip(along, after, strict=True)):
            reached = [r for r in results[2 * n:2 * n + 2] if r.refined]
            if reached:
                best = min(reached, key=lambda r: r.objectives[-1])
                placed.append(Member(best.z, best.objectives))
                self.placed += 1
            else:
                nearest = k - 1 if position - lengths[k - 1] <= lengths[k] - position else k
                placed.append(members[nearest])
        self.archive.members = []
        self.archive.add([*placed, members[-1]])
        return self.evaluations - before

    def refine(self) -> int:
        """The final refinement. Each round is one superstep: every member due a check is
        re-solved by the ε-constraint NLP (ε = its objectives, scaled by the archive's span s)
        from its own point and from each neighbour's on the front (:func:`front_neighbours`).
        The member takes what its own start reached if that dominates or equals it (as
        before); but if a neighbour's start reached a point that dominates or equals the member
        and beats the own start's by more than the tolerance (Σ_i ΔJ_i/s_i >
        :data:`~ocpar.macs.local_search.STATIONARITY_TOL`), the member moves there (the best
        such point) and is not ``settled``. Members that now dominate or repeat others drop
        out. The next round checks the members that moved and their neighbours (and members
        whose neighbours changed), until none is due, or after :data:`REFINEMENT_ROUNDS`, or
        once the rounds after the first have spent :data:`REFINEMENT_BUDGET` times the first
        round's evaluations (``rounds`` and ``extra_evaluations`` say what it took); a member
        that moved in its last check stays unsettled. A last superstep measures every
        member's Pareto stationarity (NaN if its task failed). Returns the refinement's
        evaluations."""
        span = self._span()
        before = self.evaluations
        self.rounds, first = 0, 0
        # which first-round member each current one descends from, and at its last check
        # the lineages of its neighbours; lineages moved in the round before
        lineage = {id(member): n for n, member in enumerate(self.archive.members)}
        checked: dict[int, tuple[int, ...]] = {}
        moved: set[int] = set()
        for _ in range(REFINEMENT_ROUNDS):
            members = self.archive.members
            lines = [lineage[id(member)] for member in members]
            neighbours = front_neighbours(self.archive.objectives())
            keys = [tuple(lines[j] for j in around) for around in neighbours]
            due = [i for i, key in enumerate(keys)
                   if checked.get(lines[i]) != key or moved.intersection((lines[i], *key))]
            if not due or (self.rounds and self.evaluations - before - first
                           >= REFINEMENT_BUDGET * first):
                break
            tasks = [self._task("refine", z0=members[j].z, span=span,
                                epsilon=members[i].objectives)
                     for i in due for j in (i, *neighbours[i])]
            results = iter(self._superstep(tasks))
            self.rounds += 1
            first = first or self.evaluations - before
            moved = set()
            candidates = list(members)
            for i in due:
                own, *others = [next(results) for _ in range(1 + len(neighbours[i]))]
                member = members[i]
                base = own.objectives if own.refined else member.objectives
                gains = [float(np.sum((base - r.objectives) / span)) if r.refined
                         else -np.inf for r in others]
                best = int(np.argmax(gains)) if others else -1
                beaten = best >= 0 and gains[best] > STATIONARITY_TOL
                chosen = others[best] if beaten else own
                kept = (chosen.z, chosen.objectives) if chosen.refined else (member.z,
                                                                             member.objectives)
                candidates[i] = Member(
                    *kept, member.optimised,
                    refined=bool(member.refined) or own.refined or beaten,
                    moved=bool(member.moved) or beaten,
                    improvement=(member.improvement or 0.0) + (gains[best] if beaten else 0.0),
                    settled=not beaten)
                lineage[id(candidates[i])] = lines[i]
                checked[lines[i]] = keys[i]
                if beaten:
                    moved.add(lines[i])
            self.archive.members = []
            self.archive.add(candidates)
        members = self.archive.members
        measured = self._superstep([self._task("stationarity", z0=member.z, span=span)
                                    for member in members])
        for member, result in zip(members, measured, strict=True):
            failed = result.stationarity is None  # a failed task: the residual is unknown
            member.stationarity = np.nan if failed else result.stationarity
            member.tradeoff = np.full(self.m, np.nan) if failed else result.tradeoff
        self.extra_evaluations = self.evaluations - before - first
        return self.evaluations - before

    def _move(self, agent: Agent, result: SearchResult) -> None:
        moved = agent.objectives is None or not np.allclose(
            agent.objectives, result.objectives, rtol=1e-9, atol=1e-12)
        agent.z, agent.objectives = result.z, result.objectives
        agent.decision = result.z[self.decision_slice]
        agent.fresh = agent.fresh or moved
        agent.moved = agent.moved or moved

    # -- main loop ----------------------------------------------------------------------------
    def run(self) -> MacsOutcome:
        self.initialise()
        history, fronts, iteration = [], [], 0
        while self.evaluations < self.settings.max_evaluations:
            if not self.archive.members:  # nothing feasible yet: restart from new points
                self.initialise()
            else:
                self.individualistic()
                self.social()
                self.reallocate()
            iteration += 1
            fronts.append(self.archive.objectives())
            history.append({"iteration": iteration, "evaluations": self.evaluations,
                            "archive": len(self.archive.members)})
            if self.progress:
                figure = (f"  hypervolume {self.indicator(fronts[-1]):.6f}"
                          if self.indicator and self.archive.members else "")
                self.progress(f"iteration {iteration:4d}  evaluations {self.evaluations:6d}  "
                              f"archive {len(self.archive.members):3d}{figure}")
        refinement = spread = 0
        if not self.settings.no_spread and self.archive.members:
            spread = self.spread()
        if not self.settings.no_refine and self.archive.members:
            refinement = self.refine()
            if self.progress:
                members = self.archive.members
                self.progress(f"refinement: {sum(m.refined for m in members)} of "
                              f"{len(members)} members refined, {sum(m.moved for m in members)} "
                              f"moved by a neighbour's start, {self.rounds} rounds, "
                              f"{refinement} evaluations")
        return MacsOutcome(self.archive, self.evaluations, iteration, self.failed, history,
                           fronts, refinement, self.first_failure,
                           self.rounds, self.extra_evaluations, spread, self.placed)
