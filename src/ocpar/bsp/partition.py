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
