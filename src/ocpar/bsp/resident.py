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

Placement: agent i belongs to worker slot w of :func:`~ocpar.bsp.partition.contiguous_blocks`
(n agents, the backend's worker count), fixed while the worker count is. Each worker process
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

Not (yet) done: blocks are not rebalanced by measured per-agent costs (the ``balance``
policy does not apply to resident supersteps), and a set that is never closed keeps its
states on other processes until the backend closes.
"""

from __future__ import annotations

import uuid
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from ocpar.bsp.columns import Columns
from ocpar.bsp.kernel import ChunkResult, kernel_name, resolve_kernel

if TYPE_CHECKING:
    from ocpar.bsp.backend import Backend
    from ocpar.bsp.kernel import KernelRef

#: The engine kernel that runs a :class:`ResidentChunk` in a worker (:func:`run_resident`).
RUNNER = "ocpar.bsp.resident:run_resident"
#: What a :class:`ResidentChunk` asks: solve tasks, return states, or forget the set.
STEP, COLLECT, DROP = "step", "collect", "drop"


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
    agent of ``rebuild``, in the order given) to replay."""

    what: str
    key: str
    slot: int
    kernel: str
    agents: range
    version: int
    tasks: Columns | None = None
    rebuild: np.ndarray | None = None
    history: tuple[Columns, ...] | None = None


@dataclass
class ResidentReply:
    """A worker's answer to a :class:`ResidentChunk`: the k ``results`` (a step's results,
    or the states of a collect), or, when the worker lacks some agents' states at the
    expected version and was given no history, those agents (``missing``) and no results."""

    results: Columns | list[Any] | None
    missing: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))


def run_resident(chunk: ResidentChunk) -> ResidentReply:
    """Engine kernel (:data:`RUNNER`): serve ``chunk`` from this process's store (module
    docstring)."""
    slot = (chunk.key, chunk.slot)
    if chunk.what == DROP:
        _forget(chunk.key)
        return ResidentReply(results=[])
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
    results, new_states = kernel(chunk.tasks, states)
    if len(new_states) != len(agents):
        raise ValueError(f"resident kernel {chunk.kernel} returned {len(new_states)} states "
                         f"for {len(agents)} tasks")
    _BLOCKS[slot] = _Block(agents=agents, version=chunk.version + 1, states=new_states)
    return ResidentReply(results=results)


def _forget(key: str) -> None:
    """Drop this process's blocks of the set ``key``."""
    for held in list(_BLOCKS):
        if held[0] == key:
            _BLOCKS.pop(held, None)


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


class ResidentSet:
    """n agents whose states stay on the workers of ``backend`` (module docstring), driven by
    the resident kernel ``kernel``. Use :meth:`step` once per superstep, :meth:`collect` for
    the states, :meth:`close` to free the workers' memory (the backend closes open sets when
    it closes; a set that is garbage-collected frees its states in this process at once, on
    other processes when the backend closes). Made by :meth:`~ocpar.bsp.Backend.resident`;
    runs its chunks through the backend's own chunk transport."""

    def __init__(self, backend: Backend, kernel: KernelRef, agents: int) -> None:
        if agents < 1:
            raise ValueError(f"a resident set needs at least one agent, got {agents}")
        self.backend = backend
        self.kernel = kernel_name(kernel)
        self.agents = agents
        self.key = uuid.uuid4().hex
        #: The tasks of each superstep so far (Columns of n tasks each): the agents' history.
        self.history: list[Columns] = []
        self.closed = False
        weakref.finalize(self, _forget, self.key)

    @property
    def version(self) -> int:
        """Tasks each agent has had so far."""
        return len(self.history)

    def step(self, tasks: Columns) -> Columns:
        """One superstep: task i to agent i (``tasks``: Columns of n tasks), the results in
        agent order (the kernel's results must be instances of one dataclass)."""
        if len(tasks) != self.agents:
            raise ValueError(f"{len(tasks)} tasks for {self.agents} resident agents")
        self._check_open()
        results = self.backend._resident_superstep(self, STEP, tasks)
        self.history.append(tasks)
        return results

    def collect(self) -> Columns:
        """The agents' latest states, in agent order: one superstep that moves them all to the
        coordinator (after at least one :meth:`step`)."""
        if not self.history:
            raise ValueError("no states to collect before the first step")
        self._check_open()
        return self.backend._resident_superstep(self, COLLECT, None)

    def run(self, what: str, tasks: Columns | None, groups: Sequence[range]
            ) -> list[ChunkResult]:
        """Run ``what`` for the agents of ``groups`` (group w on worker w) through the
        backend's chunks; the chunk results' ``results`` are per agent (a reply's results),
        their times are the rounds' sums (a second round if a worker lacked states)."""
        def chunk(w: int, group: range, rebuild: np.ndarray | None = None) -> ResidentChunk:
            history = None
            if rebuild is not None:
                history = tuple(t.take(rebuild) for t in self.history)
            return ResidentChunk(what=what, key=self.key, slot=w, kernel=self.kernel,
                                 agents=group, version=self.version,
                                 tasks=None if tasks is None else tasks.take(group),
                                 rebuild=rebuild, history=history)

        first = self.backend._run_chunks(RUNNER, [[chunk(w, g)] for w, g in enumerate(groups)])
        replies = [_replies(c) for c in first]
        lacking = {w: r[0].missing for w, r in enumerate(replies) if r[0].results is None}
        # a second round: each slot that lacked states, with its agents' history, to the
        # worker of its slot (or, if the backend has fewer workers now, another one)
        items: list[list[ResidentChunk]] = [[] for _ in range(self.backend.workers)]
        for w, missing in lacking.items():
            items[w % self.backend.workers].append(chunk(w, groups[w], missing))
        second = self.backend._run_chunks(RUNNER, items) if lacking else []
        for c, slots in zip(second, items if lacking else [], strict=True):
            for k, (item, reply) in enumerate(zip(slots, _replies(c), strict=True)):
                if reply.results is None:
                    raise RuntimeError(f"resident set {self.key}: slot {item.slot} still "
                                       "lacks states after its history was sent")
                replies[item.slot] = [reply]
                if k == 0:  # the worker's second round counted once, with its first slot
                    first[item.slot] = _added(first[item.slot], c)
        return [_per_agent(c, r, len(g))
                for c, r, g in zip(first, replies, groups, strict=True)]

    def close(self) -> None:
        """Forget the states on every worker (idempotent)."""
        if self.closed:
            return
        self.closed = True
        drop = ResidentChunk(what=DROP, key=self.key, slot=0, kernel=self.kernel,
                             agents=range(0), version=self.version)
        self.backend._run_chunks(RUNNER, [[drop] for _ in range(self.backend.workers)])

    def _check_open(self) -> None:
        if self.closed:
            raise RuntimeError(f"resident set {self.key} is closed")


def _replies(chunk: ChunkResult) -> list[ResidentReply]:
    """The replies of a chunk of :class:`ResidentChunk` items, in item order."""
    results = chunk.results
    return results.items() if isinstance(results, Columns) else list(results)


def _added(first: ChunkResult, second: ChunkResult) -> ChunkResult:
    """``first`` with the time and bytes of ``second`` (its worker's second round) added."""
    return ChunkResult(results=first.results, task_wall_s=[], task_cpu_s=[],
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
    return ChunkResult(results=results, task_wall_s=[chunk.busy_s / share] * k,
                       task_cpu_s=[chunk.cpu_s / share] * k, busy_s=chunk.busy_s,
                       cpu_s=chunk.cpu_s, peak_rss_mb=chunk.peak_rss_mb,
                       sent_bytes=chunk.sent_bytes, received_bytes=chunk.received_bytes)
