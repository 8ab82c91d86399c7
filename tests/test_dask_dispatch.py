"""Dask's ``direct`` dispatch (each worker's channel, started by the
``ocpar.bsp.dask_worker.ChunkChannel`` plugin): kernel errors come back as themselves, jobs
sharing a cluster get their own results, and a worker that joins later is reached too."""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from ocpar.bsp.dask import DaskBackend
from ocpar.bsp.serial import SerialBackend
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.ocp import solve_task


@pytest.fixture(scope="module")
def cluster():
    from distributed import LocalCluster

    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                      dashboard_address=":0") as cluster:
        yield cluster


def formation_tasks(agents: int, step: float):
    problem = paper_example(agents)
    return problem.tasks(problem.initial_phi() + step)


def serial_costs(tasks) -> list[float]:
    with SerialBackend() as serial:
        return serial.superstep_columns(solve_task, tasks).column("cost").tolist()


def test_a_kernel_error_reaches_the_coordinator_and_the_next_superstep_runs(cluster):
    with DaskBackend(workers=1, scheduler=cluster.scheduler_address) as backend:
        with pytest.raises(ValueError, match="math domain error"):
            backend.superstep("math:sqrt", [4.0, -1.0])
        assert backend.superstep("math:sqrt", [4.0, 2.0]) == [2.0, math.sqrt(2.0)]
        assert backend.lost_chunks == 0


def test_jobs_sharing_a_cluster_concurrently_get_their_own_results(cluster):
    """Two coordinators on one worker, superstep after superstep at the same time (their
    chunks queue on the worker's one task thread): each gets what a serial run gives."""
    jobs = [[formation_tasks(6, 0.01 * (j + 1) * k) for k in range(8)] for j in range(2)]

    def run(steps):
        with DaskBackend(workers=1, scheduler=cluster.scheduler_address) as backend:
            return [backend.superstep_columns(solve_task, t).column("cost").tolist() for t in steps]

    with ThreadPoolExecutor(2) as pool:
        got = list(pool.map(run, jobs))
    assert got == [[serial_costs(t) for t in steps] for steps in jobs]


@pytest.mark.slow
def test_a_worker_that_joins_later_runs_chunks_like_the_first(cluster):
    """The handler is a worker plugin: the scheduler gives it to a worker that joins after it
    was registered (here the second job's registration finds it there and changes nothing)."""
    tasks = formation_tasks(6, 0.05)
    with DaskBackend(workers=1, scheduler=cluster.scheduler_address):
        cluster.scale(2)
        cluster.wait_for_workers(2)
    # a worker without the handler would leave the superstep waiting until its timeout
    with DaskBackend(workers=2, scheduler=cluster.scheduler_address,
                     superstep_timeout_s=60) as backend:
        got = backend.superstep_columns(solve_task, tasks).column("cost").tolist()
        assert backend.traces[-1].worker_tasks == [3, 3]
    assert got == serial_costs(tasks)


def test_replies_are_read_as_they_arrive():
    """The coordinator reads the worker that answers first first, whatever the order it
    sent to them (the slow one's reply is unpickled after, not before)."""
    import collections
    import select
    import time

    from ocpar.bsp.channel import Channel, ChannelServer
    from ocpar.bsp.dask import _as_they_come

    servers = [ChannelServer("127.0.0.1") for _ in range(2)]
    slow, fast = (Channel(s.address) for s in servers)
    fast.send(abs, -1)
    select.select([fast], [], [], 5.0)  # its reply is in (the servers share one solve lock)
    slow.send(time.sleep, 0.5)
    waiting = {slow: collections.deque([0]), fast: collections.deque([1])}
    order = [(w, channel.receive(5.0)) for channel, w in
             _as_they_come(waiting, time.monotonic() + 5.0)]
    assert order == [(1, 1), (0, None)]
    for channel, server in zip((slow, fast), servers, strict=True):
        channel.close()
        server.close()


class _StreamLike(logging.Handler):
    """A handler whose emit takes a lock of its own, as a stream's write does: a lock Python
    does not renew in a forked child."""

    def __init__(self) -> None:
        super().__init__()
        self.stream_lock = threading.Lock()

    def emit(self, record: logging.LogRecord) -> None:
        with self.stream_lock:
            time.sleep(0.3)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="fork")
def test_a_fork_waits_for_a_thread_writing_a_log_line():
    import ocpar.bsp.dask  # noqa: F401  (registers the fork hooks)

    logger = logging.getLogger("ocpar.test.fork")
    handler = _StreamLike()
    logger.addHandler(handler)
    try:
        writer = threading.Thread(target=logger.warning, args=("a line",))
        writer.start()
        time.sleep(0.05)   # the writer is inside emit, its stream lock held
        pid = os.fork()
        if pid == 0:   # the child: its first log line must not wait for a dead thread
            os._exit(0 if handler.stream_lock.acquire(timeout=2.0) else 1)
        _, status = os.waitpid(pid, 0)
        writer.join()
        assert os.waitstatus_to_exitcode(status) == 0
    finally:
        logger.removeHandler(handler)
