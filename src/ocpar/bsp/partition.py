"""How a superstep's tasks are split among workers."""

from __future__ import annotations


def contiguous_blocks(n_tasks: int, n_workers: int) -> list[range]:
    """Split task indices 0..n_tasks-1 into n_workers contiguous blocks whose sizes differ by
    at most one. The last ``n_tasks % n_workers`` blocks get the extra task: worker 0 is also
    the coordinator under MPI."""
    if n_workers < 1:
        raise ValueError(f"need at least one worker, got {n_workers}")
    base, extra = divmod(n_tasks, n_workers)
    blocks, start = [], 0
    for w in range(n_workers):
        size = base + (1 if w >= n_workers - extra else 0)
        blocks.append(range(start, start + size))
        start += size
    return blocks


def longest_first(costs: list[float], n_workers: int) -> list[list[int]]:
    """Assign task indices to workers by longest-processing-time-first on the given cost
    estimates; ties go to the highest-numbered least-loaded worker (worker 0 also coordinates
    under MPI) and to the lower task index, so the assignment is deterministic. Each worker's
    indices come back in increasing order."""
    if n_workers < 1:
        raise ValueError(f"need at least one worker, got {n_workers}")
    loads = [0.0] * n_workers
    groups: list[list[int]] = [[] for _ in range(n_workers)]
    for i in sorted(range(len(costs)), key=lambda i: (-costs[i], i)):
        w = min(range(n_workers), key=lambda w: (loads[w], -w))
        loads[w] += costs[i]
        groups[w].append(i)
    return [sorted(g) for g in groups]
