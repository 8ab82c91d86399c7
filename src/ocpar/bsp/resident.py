"""Resident agents: per-agent state that stays in the worker process that computes it.

A scheme whose agents carry state from one superstep to the next (an inner solution that warm
starts the next solve, a path) keeps that state on the workers instead of sending it out and
back each superstep. The coordinator opens a :class:`ResidentSet` of n agents with
:meth:`~ocpar.bsp.Backend.resident`; each :meth:`ResidentSet.step` sends one task per agent
and gets back one (small) result per agent; :meth:`ResidentSet.collect` gathers the states
once, at the end.

A *resident kernel* is a plain importable function (``module:function``)
``kernel(tasks, states) -> (results, new_states)``: ``tasks`` a
:class:`~ocpar.bsp.columns.Columns` of k tasks, ``states`` the Columns of those k agents'
states after their previous task (None on their first task); it returns the k results
(Columns, or a list of instances of one dataclass: what the coordinator needs) and the k new
states (Columns: what stays).
An agent's result and new state must depend only on its own task and previous state, never
on which other agents share the call; then an agent's state is a function of its history of
tasks alone, wherever it is computed.

Reductions: a step may name a *reducer* (``module:function``) that each worker applies to
its agents' results before replying, ``reducer(results, bounds) -> rows``: ``results`` the
block's k results (Columns, agent order), ``bounds`` the row offsets of the block's
*reduction units* in them (unit j: rows bounds[j]:bounds[j+1]; units are runs of
:func:`~ocpar.bsp.partition.unit_size` consecutive agents, a function of n alone), ``rows``
one row per unit (Columns, or a list of instances of one dataclass), each computed from its
unit's results alone. The step then returns the units' rows, in unit order: a few numbers
per unit cross the network instead of an agent's outcome, and a sum over the units' rows
taken in unit order is the same number on any number of workers (e.g. the formation's outer
step, :mod:`ocpar.formation.outer_step`).

Placement: the agents are split into contiguous blocks of whole units, one per worker slot
(:attr:`ResidentSet.blocks`, at first :func:`~ocpar.bsp.partition.unit_blocks` of n
agents over the backend's workers); slot w's chunk goes to worker w. Each worker process
holds a store (module-level, :data:`_BLOCKS`) of its slots' states, keyed by the set and the
slot, with the number of tasks they have seen (the *version*). A chunk names its agents and
the version the coordinator expects; a worker that lacks some of them at that version (a
resumed run whose supersteps came from the journal, a lost Dask worker's agents now on
another worker, a changed worker count) answers which ones instead of solving, and the
coordinator sends the chunk again with those agents' earlier tasks (the set's history,
kept on the coordinator: one task per agent per superstep): the worker replays them to
rebuild the states, then solves. Replaying gives the same states bit for bit, so results
never depend on placement, worker count, faults or resumption. The history costs the
coordinator one task per agent per superstep in memory (100,000 formation agents: 6.4 MB for
the first superstep, 1.6 MB for each later one) and is only sent where a worker lacks states.

Rebalancing: the blocks follow the agents' measured costs. After each step an agent's cost
is estimated as its slot's busy time over the slot's agents (a batched kernel times no finer),
a piecewise-constant cost over agent ids, kept per reduction unit (the unit's agents' sum: a
few thousand numbers at any n, so that the coordinator's bookkeeping does not grow with the
agents), averaged over the steps (:data:`COST_SMOOTHING`)
from the second step on (the first step's times, which include building the workers'
solvers, serve until then; a slot that took in agents in a step keeps its agents' estimates:
its time includes building solvers for the newcomers' shapes), and so, from the third step
on, is how far the slots' measured times stray from their estimates (the *noise*, relative
to the mean slot's time). Before a step the
coordinator asks :meth:`ResidentSet.rebalanced` whether blocks of whole units of equal
estimated cost (:func:`~ocpar.bsp.partition.unit_blocks`) pay: the current blocks' estimated
imbalance (max/mean load) must exceed 1 + the backend's
:attr:`~ocpar.bsp.Backend.resident_tolerance` (default
:data:`~ocpar.bsp.partition.AFFINITY_TOLERANCE`, None: fixed blocks; ``--resident-blocks``
on the command lines) + the noise (:data:`INITIAL_NOISE` until measured: an imbalance the
timings' noise could make is no reason to move), and the makespan they save in one superstep
must exceed the estimated cost of moving the leaving agents' states (:data:`MOVE_SECONDS`
plus their bytes, as the workers report them, times :data:`MOVE_SECONDS_PER_BYTE`); never
with one worker. A move
takes no superstep of its own: in that step each old worker solves its old block, returns the
leaving agents' new states with its reply (``export``) and forgets them; the next superstep's
chunks (a step's or a collect's) carry them to their new workers (``imports``), which merge
them with the states they hold. The states travel in the chunks, so the traces' bytes count
them; a planned move never replays history (a worker lost with states in flight is a fault
like any other: the moved states still arrive, the lost ones are replayed). The moves depend
on timings, the results do not: an agent's state is a function of its own tasks.

Not (yet) done: a set that is never closed keeps its states on other processes until the
backend closes; the ``balance`` policy does not apply to resident supersteps (their blocks
follow the measured costs instead).
"""

from __future__ import annotations

import uuid
import weakref
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from ocpar.bsp.columns import LISTED, SHARED, Columns, to_columns
from ocpar.bsp.kernel import ChunkResult, kernel_name, resolve_kernel
from ocpar.bsp.partition import block_loads, unit_blocks, unit_size

if TYPE_CHECKING:
    from ocpar.bsp.kernel import KernelRef

#: The engine kernel that runs a :class:`ResidentChunk` in a worker (:func:`run_resident`).
RUNNER = "ocpar.bsp.resident:run_resident"
#: What a :class:`ResidentChunk` asks: solve tasks, return states, apply a function to the
#: states, or forget the set.
STEP, COLLECT, APPLY, DROP = "step", "collect", "apply", "drop"
#: Weight of the latest step's measurement in an agent's estimated cost (an exponential
#: average over the steps: one slow step of a worker moves its agents' estimates by half).
COST_SMOOTHING = 0.5
#: The relative noise of a slot's measured time assumed until a second step measures it
#: (then :attr:`ResidentSet.noise`, measured): uniform formation agents' slots measured ±10 %
#: from one superstep to the next on this 2-core machine with another process running.
INITIAL_NOISE = 0.1
#: Estimated seconds per byte of state an agent move costs: the old worker's reply and the
#: new worker's chunk each carry it (pickled, sent and unpickled twice). Conservative: 10 ns,
#: where pickling and unpickling the formation's states measured 0.14 ns per byte (850 bytes
#: per mixed-fleet agent) and moving 290 kB of them in a Dask superstep added less than the
#: superstep's few-ms noise, on this 2-core machine (2026-12).
MOVE_SECONDS_PER_BYTE = 1e-8
#: Estimated fixed cost (s) of moving blocks, whatever they carry: the old and new workers'
#: bookkeeping, and a margin for a superstep's timing noise (its overhead, wall − busiest
#: worker, measured ~0.6 ms on MPI and ~1.9 ms on Dask at 1000 agents): a move must save more.
MOVE_SECONDS = 1e-3


@dataclass
class _Block:
    """The states (Columns, one row per agent of ``agents``) of one slot after ``version``
    tasks."""

    agents: np.ndarray
    version: int
    states: Columns


#: This process's resident states: (set key, slot) → block.
_BLOCKS: dict[tuple[str, int], _Block] = {}


@dataclass(frozen=True)
class ResidentChunk:
    """One worker's share of a resident superstep: ``what`` (:data:`STEP`, :data:`COLLECT` or
    :data:`DROP`) for the agents ``agents`` (a range: their ids) of slot ``slot`` of the
    set ``key`` (run-unique), whose resident kernel is ``kernel``; each agent has had
    ``version`` tasks before. ``tasks``: the k tasks of a step. ``history``: where the
    worker lacked agents, each of their earlier tasks (``version`` Columns, one row per
    agent of ``rebuild``, in the order given) to replay. ``imported``: agents that move into
    the slot, their states (after ``version`` tasks) in ``imports`` (one row each, in the
    order given); ``export``: agents that leave the slot after this step, their new states
    to be returned and forgotten. ``function``: a step's reducer (module docstring), which
    gets the block's units of ``unit`` agents (``agents`` starts at a unit's first), or the
    function :meth:`ResidentSet.apply` applies."""

    what: str
    key: str
    slot: int
    kernel: str
    agents: range
    version: int
    tasks: Columns | None = None
    rebuild: np.ndarray | None = None
    history: tuple[Columns, ...] | None = None
    imported: np.ndarray | None = None
    imports: Columns | None = None
    export: np.ndarray | None = None
    function: str | None = None
    unit: int = 1


@dataclass
class ResidentReply:
    """A worker's answer to a :class:`ResidentChunk`: the k ``results`` (a step's results,
    or the states of a collect), or, when the worker lacks some agents' states at the
    expected version and was given no history, those agents (``missing``) and no results.
    After a step: the new states of the chunk's ``export`` agents (``exported``, in agent
    order) and the size of all k new states (``state_bytes``, their arrays' bytes)."""

    results: Columns | list[Any] | None
    missing: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    exported: Columns | None = None
    state_bytes: int = 0


def run_resident(chunk: ResidentChunk) -> ResidentReply:
    """Engine kernel (:data:`RUNNER`): serve ``chunk`` from this process's store (module
    docstring)."""
    slot = (chunk.key, chunk.slot)
    if chunk.what == DROP:
        _forget(chunk.key)
        return ResidentReply(results=[])
    if chunk.imported is not None:
        _BLOCKS[slot] = _merged(_BLOCKS.get(slot), chunk)
    if not len(chunk.agents):
        return ResidentReply(results=[])
    kernel = resolve_kernel(chunk.kernel)
    agents = np.arange(chunk.agents.start, chunk.agents.stop, dtype=np.int64)
    states, missing = _lookup(_BLOCKS.get(slot), agents, chunk.version)
    if len(missing):
        if chunk.history is None or chunk.rebuild is None:
            return ResidentReply(results=None, missing=missing)
        states = _rebuilt(kernel, agents, chunk, states)
    if chunk.what == COLLECT:
        return ResidentReply(results=states)
    assert chunk.tasks is not None
    if chunk.what == APPLY:
        return ResidentReply(results=resolve_kernel(chunk.function)(chunk.tasks, states))
    results, new_states = kernel(chunk.tasks, states)
    if len(new_states) != len(agents):
        raise ValueError(f"resident kernel {chunk.kernel} returned {len(new_states)} states "
                         f"for {len(agents)} tasks")
    if chunk.function is not None:
        bounds = np.append(np.arange(0, len(agents), chunk.unit), len(agents))
        results = resolve_kernel(chunk.function)(to_columns(results), bounds)
    size, exported = _nbytes(new_states), None
    if chunk.export is not None and len(chunk.export):
        leaving = np.isin(agents, chunk.export)
        exported = new_states.take(np.flatnonzero(leaving))
        agents, new_states = agents[~leaving], new_states.take(np.flatnonzero(~leaving))
    _BLOCKS[slot] = _Block(agents=agents, version=chunk.version + 1, states=new_states)
    return ResidentReply(results=results, exported=exported, state_bytes=size)


def _forget(key: str) -> None:
    """Drop this process's blocks of the set ``key``."""
    for held in list(_BLOCKS):
        if held[0] == key:
            _BLOCKS.pop(held, None)


def _merged(block: _Block | None, chunk: ResidentChunk) -> _Block:
    """``block`` (if at the chunk's version) with the chunk's imported states: the agents
    in increasing order (a chunk sent twice merges its imports once)."""
    assert chunk.imported is not None and chunk.imports is not None
    if block is None or block.version != chunk.version:
        return _Block(agents=chunk.imported, version=chunk.version, states=chunk.imports)
    kept = np.flatnonzero(~np.isin(block.agents, chunk.imported))
    agents = np.concatenate([block.agents[kept], chunk.imported])
    order = np.argsort(agents, kind="stable")
    states = Columns.concat([block.states.take(kept), chunk.imports]).take(order)
    return _Block(agents=agents[order], version=chunk.version, states=states)


def _nbytes(states: Columns) -> int:
    """The bytes of ``states``' arrays (a shared value counted once, a listed one as 8)."""
    total = 0
    for kind, data in states.fields.values():
        if kind == SHARED:
            total += getattr(data, "nbytes", 8)
        elif kind == LISTED:
            total += sum(getattr(value, "nbytes", 8) for value in data)
        else:
            total += data.nbytes
    return total


def _lookup(block: _Block | None, agents: np.ndarray, version: int
            ) -> tuple[Columns | None, np.ndarray]:
    """The states of ``agents`` after ``version`` tasks that ``block`` holds (None: none, or
    no task yet) and the agents it lacks."""
    if version == 0:
        return None, np.zeros(0, np.int64)
    if block is None or block.version != version:
        return None, agents
    if np.array_equal(block.agents, agents):
        return block.states, np.zeros(0, np.int64)
    held = np.isin(agents, block.agents)
    return block.states.take(np.searchsorted(block.agents, agents[held])), agents[~held]


def _rebuilt(kernel: Any, agents: np.ndarray, chunk: ResidentChunk, held: Columns | None
             ) -> Columns:
    """The states of all of ``agents`` (the chunk's): ``held`` (the rows of those the
    worker had, in agent order) and the others replayed from ``chunk.history``."""
    assert chunk.history is not None and chunk.rebuild is not None
    states = None
    for tasks in chunk.history:
        _, states = kernel(tasks, states)
    assert states is not None
    have = ~np.isin(agents, chunk.rebuild)
    if not have.any():
        return states
    order = np.concatenate([agents[have], chunk.rebuild])
    return Columns.concat([held, states]).take(np.argsort(order, kind="stable"))  # type: ignore[list-item]


@dataclass(frozen=True)
class _Moving:
    """States on their way between slots: those of ``agents`` (increasing) after ``version``
    tasks, one row each in ``states``, returned by their old workers, for their new ones."""

    agents: np.ndarray
    version: int
    states: Columns

    def into(self, group: range) -> tuple[np.ndarray, Columns] | None:
        """The agents of ``group`` among these and their states (None: none)."""
        rows = np.flatnonzero((self.agents >= group.start) & (self.agents < group.stop))
        return (self.agents[rows], self.states.take(rows)) if len(rows) else None


class ResidentHost(Protocol):
    """What a :class:`ResidentSet` needs of its backend (:class:`~ocpar.bsp.Backend` is one):
    its worker count, its rebalancing tolerance, its chunk transport and its superstep of a
    resident set. A protocol, so that this module does not import the backend's."""

    workers: int
    resident_tolerance: float | None

    def _run_chunks(self, name: str, chunks: list[list[Any] | Columns]) -> list[ChunkResult]:
        ...

    def _resident_superstep(self, resident: ResidentSet, what: str, tasks: Columns | None
                            ) -> Any:
        ...


class ResidentSet:
    """n agents whose states stay on the workers of ``backend`` (module docstring), driven by
    the resident kernel ``kernel``. Use :meth:`step` once per superstep, :meth:`collect` for
    the states, :meth:`close` to free the workers' memory (the backend closes open sets when
    it closes; a set that is garbage-collected frees its states in this process at once, on
    other processes when the backend closes). Made by :meth:`~ocpar.bsp.Backend.resident`;
    runs its chunks through the backend's own chunk transport. Its blocks move between steps
    by the agents' measured costs, by the backend's
    :attr:`~ocpar.bsp.Backend.resident_tolerance` (module docstring)."""

    def __init__(self, backend: ResidentHost, kernel: KernelRef, agents: int) -> None:
        if agents < 1:
            raise ValueError(f"a resident set needs at least one agent, got {agents}")
        self.backend = backend
        self.kernel = kernel_name(kernel)
        self.agents = agents
        self.key = uuid.uuid4().hex
        #: The tasks of each superstep so far (Columns of n tasks each): the agents' history.
        self.history: list[Columns] = []
        #: Each worker slot's agents (contiguous ranges of whole reduction units, in slot
        #: order) at the next superstep.
        self.blocks: list[range] = unit_blocks(agents, backend.workers)
        #: Each reduction unit's estimated solve time (s, one per unit): its
        #: agents' share of their slot's busy time, averaged over the steps measured
        #: (:data:`COST_SMOOTHING`); None before the first.
        self.costs: np.ndarray | None = None
        #: Agents per reduction unit (:func:`~ocpar.bsp.partition.unit_size`).
        self.unit = unit_size(agents)
        #: The agents of each reduction unit (all :attr:`unit` but the last).
        self.unit_lengths = np.diff(np.append(np.arange(0, agents, self.unit), agents))
        #: How far a step's measured slot times stray from their estimates, relative to the
        #: mean slot's (averaged like the costs; :data:`INITIAL_NOISE` until measured).
        self.noise = INITIAL_NOISE
        #: The mean bytes of an agent's state, as the workers last reported them.
        self.state_bytes = 0.0
        #: Agents moved to another slot so far.
        self.moved = 0
        self._moving: _Moving | None = None
        self.closed = False
        weakref.finalize(self, _forget, self.key)

    @property
    def version(self) -> int:
        """Tasks each agent has had so far."""
        return len(self.history)

    def step(self, tasks: Columns, reduce: KernelRef | None = None) -> Columns:
        """One superstep: task i to agent i (``tasks``: Columns of n tasks; a field shared
        by all of them travels once per worker), the results in agent order (the kernel's
        results must be instances of one dataclass), or with a reducer ``reduce``
        (``module:function``, module docstring) one row per reduction unit, in unit
        order."""
        if len(tasks) != self.agents:
            raise ValueError(f"{len(tasks)} tasks for {self.agents} resident agents")
        self._check_open()
        results = self.backend._resident_superstep(
            self, STEP, tasks, None if reduce is None else kernel_name(reduce))
        self.history.append(tasks)
        return results

    def collect(self) -> Columns:
        """The agents' latest states, in agent order: one superstep that moves them all to the
        coordinator (after at least one :meth:`step`)."""
        if not self.history:
            raise ValueError("no states to collect before the first step")
        self._check_open()
        return self.backend._resident_superstep(self, COLLECT, None)

    def apply(self, function: KernelRef, tasks: Columns) -> Columns:
        """``function(tasks, states)`` on every worker for its agents (``tasks``: Columns of n
        tasks; the states as the last step left them), the results (one per agent, instances
        of one dataclass) in agent order. Not a superstep: the states stay as they are, and
        it is neither traced nor journaled (a resumed run applies it again, to the states
        its history rebuilds); for what a run does with its answer once it has it (the
        formation checks and writes its agents' paths where they are,
        :mod:`ocpar.formation.finish`)."""
        if len(tasks) != self.agents:
            raise ValueError(f"{len(tasks)} tasks for {self.agents} resident agents")
        if not self.history:
            raise ValueError("no states to apply a function to before the first step")
        self._check_open()
        _, chunks = self.run(APPLY, tasks, kernel_name(function))
        parts = [to_columns(c.results) for c in chunks if len(c.results)]
        return Columns.concat(parts)  # type: ignore[arg-type]

    def run(self, what: str, tasks: Columns | None, function: str | None = None
            ) -> tuple[list[range], list[ChunkResult]]:
        """Run ``what`` for every agent through the backend's chunks, slot w's agents
        (:attr:`blocks`) on worker w, with the states moving into each slot; a step also
        moves the blocks where that pays (:meth:`rebalanced`: the leaving agents' new states
        come back with the replies, for the next superstep's chunks). Returns the blocks run
        and the chunk results, whose ``results`` are per agent (a reply's results; a step's
        with a reducer ``function``, per unit) and whose times are the rounds' sums (a second
        round if a worker lacked states)."""
        if len(self.blocks) != self.backend.workers:  # the worker count changed
            self.blocks, self.costs = unit_blocks(self.agents, self.backend.workers), None
        groups = self.blocks
        following = self.rebalanced() if what == STEP else groups
        moving, self._moving = self._moving, None
        if moving is not None and moving.version != self.version:
            moving = None  # supersteps replayed from the journal since: the history rebuilds
        arriving = [moving.into(g) if moving is not None else None for g in groups]
        leaving = [_outside(g, f) for g, f in zip(groups, following, strict=True)]

        def chunk(w: int, rebuild: np.ndarray | None = None) -> ResidentChunk:
            group, imported = groups[w], arriving[w]
            history = None
            if rebuild is not None:
                history = tuple(t.take(rebuild) for t in self.history)
            return ResidentChunk(what=what, key=self.key, slot=w, kernel=self.kernel,
                                 agents=group, version=self.version,
                                 tasks=None if tasks is None else tasks.take(group),
                                 rebuild=rebuild, history=history,
                                 imported=None if imported is None else imported[0],
                                 imports=None if imported is None else imported[1],
                                 export=leaving[w] if len(leaving[w]) else None,
                                 function=function, unit=self.unit)

        first = self.backend._run_chunks(RUNNER, [[chunk(w)] for w in range(len(groups))])
        replies = [_replies(c) for c in first]
        lacking = {w: r[0].missing for w, r in enumerate(replies) if r[0].results is None}
        # a second round: each slot that lacked states, with its agents' history, to the
        # worker of its slot (or, if the backend has fewer workers now, another one)
        items: list[list[ResidentChunk]] = [[] for _ in range(self.backend.workers)]
        for w, missing in lacking.items():
            items[w % self.backend.workers].append(chunk(w, missing))
        second = self.backend._run_chunks(RUNNER, items) if lacking else []
        for c, slots in zip(second, items if lacking else [], strict=True):
            for k, (item, reply) in enumerate(zip(slots, _replies(c), strict=True)):
                if reply.results is None:
                    raise RuntimeError(f"resident set {self.key}: slot {item.slot} still "
                                       "lacks states after its history was sent")
                replies[item.slot] = [reply]
                if k == 0:  # the worker's second round counted once, with its first slot
                    first[item.slot] = _added(first[item.slot], c)
        if what == STEP:
            self._moved_on(following, leaving, [r[0] for r in replies])
            if not lacking:  # a replay's time is not the agents' cost
                self._measure(groups, [c.busy_s for c in first],
                              [imported is not None for imported in arriving])
        return groups, [_per_agent(c, r, len(g))
                        for c, r, g in zip(first, replies, groups, strict=True)]

    def rebalanced(self) -> list[range]:
        """The blocks for the superstep after the next one: those that equalise the agents'
        estimated :attr:`costs` over whole units (:func:`~ocpar.bsp.partition.unit_blocks`)
        if the
        current blocks' estimated imbalance (max/mean load) exceeds 1 + the backend's
        :attr:`~ocpar.bsp.Backend.resident_tolerance` + the measurements' :attr:`noise` and
        the makespan they save in one superstep exceeds the estimated cost of moving the
        states (:data:`MOVE_SECONDS` and :data:`MOVE_SECONDS_PER_BYTE`); otherwise the
        current ones (always with one worker, no estimates yet, or a tolerance of None)."""
        tolerance = self.backend.resident_tolerance
        if tolerance is None or self.costs is None or len(self.blocks) < 2:
            return self.blocks
        loads = block_loads(self.costs, self._in_units(self.blocks))
        heaviest, mean = loads.max(), loads.mean()
        if heaviest <= (1.0 + tolerance + self.noise) * mean:
            return self.blocks
        # no blocks' makespan is below the mean load (but by rounding, far below 1 ns): blocks
        # can save at most the excess over the mean; below a move's fixed cost, none pays
        if heaviest - mean < MOVE_SECONDS * (1.0 - 1e-6):
            return self.blocks
        proposed = unit_blocks(self.agents, len(self.blocks), self.costs)
        saving = heaviest - block_loads(self.costs, self._in_units(proposed)).max()
        staying = sum(max(0, min(a.stop, b.stop) - max(a.start, b.start))
                      for a, b in zip(self.blocks, proposed, strict=True))
        moving_s = MOVE_SECONDS + (self.agents - staying) * self.state_bytes * MOVE_SECONDS_PER_BYTE
        return proposed if saving > moving_s else self.blocks

    def _moved_on(self, following: list[range], leaving: list[np.ndarray],
                  replies: list[ResidentReply]) -> None:
        """After a step: the blocks are ``following``, the states of ``leaving`` (per slot)
        that ``replies`` returned on their way to their new slots."""
        self.state_bytes = sum(r.state_bytes for r in replies) / self.agents
        self.blocks = following
        exported = [r.exported for r in replies if r.exported is not None]
        if exported:
            agents = np.concatenate(leaving)
            states = Columns.concat(exported)
            if len(states) != len(agents):
                raise RuntimeError(f"resident set {self.key}: {len(states)} states came back "
                                   f"for {len(agents)} leaving agents")
            self._moving = _Moving(agents=agents, version=self.version + 1, states=states)
            self.moved += len(agents)

    def _in_units(self, blocks: list[range]) -> list[range]:
        """``blocks`` of whole units (agent ranges) as ranges of unit indices."""
        size = self.unit
        return [range(b.start // size, -(-b.stop // size)) for b in blocks]

    def _measure(self, groups: list[range], busy_s: list[float], arrived: list[bool]) -> None:
        """Update the units' estimated :attr:`costs` and the :attr:`noise` by a step's busy
        time per slot, but for the slots where agents ``arrived`` (a worker's first solves of
        an agent's shape build its solver: not the agents' cost), whose units keep their
        estimates."""
        units = self._in_units(groups)
        counts = [len(u) for u in units]
        per_agent = [b / max(len(g), 1) for b, g in zip(busy_s, groups, strict=True)]
        sample = np.repeat(per_agent, counts) * self.unit_lengths
        if self.costs is None or self.version == 1:  # the first step's times, which include
            self.costs = sample                        # building the solvers, until the next
            return
        expected = block_loads(self.costs, units)
        stray = np.abs(np.asarray(busy_s) - expected)  # per slot (s)
        averaged = COST_SMOOTHING * sample + (1.0 - COST_SMOOTHING) * self.costs
        if any(arrived):  # masks only then (the usual step measures every slot)
            settled = np.logical_not(arrived)
            stray = stray[settled]
            averaged = np.where(np.repeat(settled, counts), averaged, self.costs)
        mean = expected.mean()
        if len(stray) and mean > 0:
            self.noise = COST_SMOOTHING * (stray.max() / mean) + (1.0 - COST_SMOOTHING) * self.noise
        self.costs = averaged

    def close(self) -> None:
        """Forget the states on every worker (idempotent)."""
        if self.closed:
            return
        self.closed = True
        self._moving = None
        drop = ResidentChunk(what=DROP, key=self.key, slot=0, kernel=self.kernel,
                             agents=range(0), version=self.version)
        self.backend._run_chunks(RUNNER, [[drop] for _ in range(self.backend.workers)])

    def _check_open(self) -> None:
        if self.closed:
            raise RuntimeError(f"resident set {self.key} is closed")


def _outside(group: range, block: range) -> np.ndarray:
    """The agents of ``group`` that are not in ``block``, in increasing order (the work of
    the agents that leave, not of the group's)."""
    return np.concatenate([np.arange(group.start, min(group.stop, block.start), dtype=np.int64),
                           np.arange(max(group.start, block.stop), group.stop, dtype=np.int64)])


def _replies(chunk: ChunkResult) -> list[ResidentReply]:
    """The replies of a chunk of :class:`ResidentChunk` items, in item order."""
    results = chunk.results
    return results.items() if isinstance(results, Columns) else list(results)


def _added(first: ChunkResult, second: ChunkResult) -> ChunkResult:
    """``first`` with the time and bytes of ``second`` (its worker's second round) added."""
    return ChunkResult(results=first.results, task_wall_s=np.zeros(0), task_cpu_s=np.zeros(0),
                       busy_s=first.busy_s + second.busy_s, cpu_s=first.cpu_s + second.cpu_s,
                       peak_rss_mb=max(first.peak_rss_mb, second.peak_rss_mb),
                       sent_bytes=first.sent_bytes + second.sent_bytes,
                       received_bytes=first.received_bytes + second.received_bytes)


def _per_agent(chunk: ChunkResult, replies: list[ResidentReply], k: int) -> ChunkResult:
    """``chunk``'s time with its reply's results (one per agent, k agents), the time shared
    equally among the agents, as for a batched kernel."""
    (reply,) = replies
    results = reply.results if reply.results is not None else []
    share = max(k, 1)
    return ChunkResult(results=results, task_wall_s=np.full(k, chunk.busy_s / share),
                       task_cpu_s=np.full(k, chunk.cpu_s / share), busy_s=chunk.busy_s,
                       cpu_s=chunk.cpu_s, peak_rss_mb=chunk.peak_rss_mb,
                       sent_bytes=chunk.sent_bytes, received_bytes=chunk.received_bytes)
