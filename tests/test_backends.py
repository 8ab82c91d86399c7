"""The engine: same results in task order on every backend; the formation run agrees to 1e-10
across serial, mpirun -n 2, embedded Dask and an external Dask cluster."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from conftest import run_cli

from ocpar.bsp import contiguous_blocks, kernel_name, open_backend
from ocpar.bsp.backend import BackendError
from ocpar.bsp.columns import Columns, to_columns
from ocpar.bsp.partition import longest_first
from ocpar.examples.formation_point_masses import make as paper_example
from ocpar.formation import solve_formation
from ocpar.models import PointMass
from ocpar.ocp import DmocShape, OcpTask
from ocpar.result_files import load_trace

SHAPE = DmocShape(PointMass(), 10)


def dmoc_tasks(n: int) -> list[OcpTask]:
    rng = np.random.default_rng(1)
    return [OcpTask(SHAPE, rng.standard_normal(8)) for _ in range(n)]


def test_contiguous_blocks_cover_tasks_in_order():
    blocks = contiguous_blocks(10, 3)
    assert [list(b) for b in blocks] == [[0, 1, 2, 3], [4, 5, 6], [7, 8, 9]]
    assert [len(b) for b in contiguous_blocks(2, 4)] == [1, 1, 0, 0]  # extra to worker 0 first
    with pytest.raises(ValueError):
        contiguous_blocks(3, 0)


def test_longest_first_balances_and_gives_ties_to_worker_0():
    # under MPI worker 0 is the coordinator's process: its chunk crosses no message
    assert longest_first([12, 44, 59, 59, 59], 2) == [[2, 4], [0, 1, 3]]  # loads 118 vs 115
    assert [len(g) for g in longest_first([1.0] * 5, 2)] == [3, 2]
    assert longest_first([], 3) == [[], [], []]


def test_cost_balanced_superstep_keeps_task_order(local_dask):
    values = [float(v) for v in range(1, 8)]
    got = local_dask.superstep("math:sqrt", values, costs=[7, 1, 6, 2, 5, 3, 4])
    assert got == [v**0.5 for v in values]
    assert sorted(local_dask.traces[-1].worker_tasks) == [3, 4]
    with pytest.raises(ValueError, match="costs"):
        local_dask.superstep("math:sqrt", values, costs=[1.0])


def test_kernel_must_be_importable():
    assert kernel_name(math.sqrt) == "math:sqrt"
    with pytest.raises(ValueError, match="module-level"):
        kernel_name(lambda x: x)
    with pytest.raises(ValueError, match="module:function"):
        kernel_name("sqrt")


def test_serial_superstep_is_timed():
    with open_backend("serial") as backend:
        assert backend.superstep("math:sqrt", [4.0, 9.0]) == [2.0, 3.0]
        trace = backend.traces[0]
    assert trace.tasks == 2 and trace.worker_tasks == [2]
    assert len(trace.task_wall_s) == 2 and trace.wall_s >= trace.worker_busy_s[0] > 0
    assert trace.to_dict()["overhead_s"] >= 0


def test_unknown_backend_is_refused():
    with pytest.raises(BackendError, match="unknown backend"):
        open_backend("threads")
    with pytest.raises(BackendError, match="unknown balance policy"):
        open_backend("serial", balance="random")


@pytest.mark.slow  # asserts measured timings (imbalance, stickiness): noisy on a busy 2-core box
def test_lpt_balances_a_heterogeneous_workload_with_the_same_results():
    """Tasks of 3, 6, …, 36 ms: contiguous blocks give one worker 63 ms and the other 171 ms
    (max/mean busy 1.46); from the second superstep on, LPT on the measured times balances
    them (≤ 1.1), keeps most tasks on their worker, and the results are unchanged."""
    seconds = [0.003 * (i + 1) for i in range(12)]
    with open_backend("dask", workers=2, balance="lpt") as backend:
        results = [backend.superstep("ocpar.bsp.workload:spin", seconds) for _ in range(3)]
        first, *later = backend.traces
    assert all(r == seconds for r in results)
    assert first.task_worker.tolist() == [0] * 6 + [1] * 6 and first.imbalance > 1.3
    for trace in later:
        assert trace.imbalance < 1.1, trace.worker_busy_s
    # 10 of 12 tasks stay where they were (only tasks 7 and 8 move to worker 0)
    kept = np.equal(later[0].task_worker, first.task_worker)
    assert kept.sum() == 10
    # balanced: at most a timing hiccup (a task measured longer than it is) moves one again
    assert np.equal(later[1].task_worker, later[0].task_worker).sum() >= 10


@pytest.fixture(scope="module")
def local_dask():
    with open_backend("dask", workers=2) as backend:
        yield backend


def test_dask_results_in_task_order_and_equal_to_serial(local_dask):
    tasks = dmoc_tasks(7)
    with open_backend("serial") as serial:
        expected = serial.superstep("ocpar.ocp:solve_task", tasks)
    got = local_dask.superstep("ocpar.ocp:solve_task", tasks)
    assert [g.cost for g in got] == [e.cost for e in expected]  # bitwise
    trace = local_dask.traces[-1]
    assert trace.worker_tasks == [4, 3] and len(trace.task_cpu_s) == 7


def _solution_bytes(solutions) -> list[tuple]:
    return [(s.cost, s.cost_gradient.tobytes(), s.q.tobytes(), s.u.tobytes(), s.status,
             s.success, s.iterations) for s in solutions]


@pytest.mark.parametrize("costs", [None, [1, 5, 2, 8, 3, 9, 4]])
def test_columnar_superstep_equals_the_list_superstep(local_dask, costs):
    """superstep_columns gives the same solutions in task order as superstep, bit for bit,
    on the serial backend and on Dask, with contiguous blocks and with longest-first (tasks
    reordered across workers)."""
    tasks = dmoc_tasks(7)
    columns = to_columns(tasks)
    with open_backend("serial") as serial:
        expected = _solution_bytes(serial.superstep("ocpar.ocp:solve_task", tasks))
        got_serial = serial.superstep_columns("ocpar.ocp:solve_task", columns, costs)
    got_dask = local_dask.superstep_columns("ocpar.ocp:solve_task", columns, costs)
    for got in (got_serial, got_dask):
        assert isinstance(got, Columns) and got.column("q").shape == (7, 11, 2)
        assert _solution_bytes(got.items()) == expected
    assert local_dask.traces[-1].tasks == 7 and len(local_dask.traces[-1].task_worker) == 7
    with pytest.raises(TypeError, match="not instances of one dataclass"):
        local_dask.superstep_columns("builtins:repr", to_columns([SHAPE]))
    with pytest.raises(ValueError, match="non-empty Columns"):
        local_dask.superstep_columns("math:sqrt", [4.0])


def test_dask_task_dispatch_equals_direct_dispatch(local_dask):
    """The two ways of handing chunks to Dask workers give bit-identical results."""
    from ocpar.bsp.dask import DaskBackend

    tasks = dmoc_tasks(5)
    direct = local_dask.superstep("ocpar.ocp:solve_task", tasks)
    scheduler = local_dask.client.scheduler.address
    with DaskBackend(workers=2, scheduler=scheduler, dispatch="tasks") as backend:
        via_tasks = backend.superstep("ocpar.ocp:solve_task", tasks)
    assert [t.cost for t in via_tasks] == [d.cost for d in direct]
    with pytest.raises(BackendError, match="unknown dispatch"):
        DaskBackend(workers=1, scheduler=scheduler, dispatch="rpc")


def test_dask_workers_build_each_solver_once(local_dask):
    """Build once, solve many: once a worker process has this shape's DMOC solver (built in
    its first superstep, or inherited from the process it was forked from), further
    supersteps build nothing, and always the same worker gets the same chunk."""
    local_dask.superstep("ocpar.ocp:solve_task", dmoc_tasks(4))
    before = local_dask.superstep("ocpar.ocp:cache_report", [None, None])
    for _ in range(3):
        local_dask.superstep("ocpar.ocp:solve_task", dmoc_tasks(4))
    after = local_dask.superstep("ocpar.ocp:cache_report", [None, None])
    assert len({r["pid"] for r in after}) == 2
    assert [r["pid"] for r in after] == [r["pid"] for r in before]
    assert all(a["builds"] == b["builds"] and a["hits"] >= b["hits"] + 6
               for a, b in zip(after, before, strict=True))


@pytest.fixture(scope="module")
def serial_reference():
    return solve_formation(paper_example(agents=60))


def assert_same_run(data: dict, reference) -> None:
    assert data["status"] == "converged"
    assert data["total_cost"] == pytest.approx(reference.total_cost, rel=1e-10)
    np.testing.assert_allclose(data["phi"], reference.phi, rtol=1e-10, atol=1e-12)
    assert data["supersteps"] == reference.supersteps


def test_mpirun_two_ranks_matches_serial(serial_reference, tmp_path):
    proc = run_cli("-m", "ocpar.formation", "--output", str(tmp_path), mpi_ranks=2)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "mpi" and data["workers"] == 2
    assert_same_run(data, serial_reference)
    # the blocks start even; measured costs may move agents later (a descheduled rank looks
    # slow), which never changes a bit of the result (tests/test_rebalance.py)
    tasks = [t["worker_tasks"] for t in load_trace(tmp_path)]
    assert tasks[0] == [30, 30] and all(sum(t) == 60 and min(t) > 0 for t in tasks), tasks
    assert proc.stdout.count("superstep ") == data["supersteps"]


MPI_QUEUE = """
import json
from ocpar.bsp.mpi import MpiBackend
backend = MpiBackend()
if backend.is_coordinator:
    out = []
    for seconds, costs in (([0.04, 0.001, 0.03, 0.002, 0.02, 0.003, 0.01], "true"),
                           ([0.001, 0.002, 0.003], None), ([0.02, 0.001, 0.01], "true"),
                           ([0.5, 0.001, 0.002, 0.003], "equal")):
        estimates = {None: None, "true": seconds, "equal": [1.0] * len(seconds)}[costs]
        got = backend.superstep("ocpar.bsp.workload:spin", seconds, costs=estimates)
        trace = backend.traces[-1]
        out.append({"sent": seconds, "got": got, "task_worker": trace.task_worker.tolist(),
                    "worker_tasks": trace.worker_tasks})
    backend.close()
    print(json.dumps(out))
else:
    backend.serve()
"""


def test_mpi_ranks_take_costed_tasks_from_a_shared_queue(tmp_path):
    """Given costs, MPI ranks take tasks longest-first from a shared counter: every task runs
    once, results come back in task order, superstep after superstep (with and without
    costs in between). With equal estimates for a 0.5 s task and three of 1-3 ms, the rank
    that runs the long one runs nothing else (assigned in advance, it would get two of the
    four)."""
    script = tmp_path / "queue.py"
    script.write_text(MPI_QUEUE)
    proc = run_cli(str(script), mpi_ranks=2, timeout=120)
    assert proc.returncode == 0, proc.stderr
    steps = json.loads(proc.stdout.strip().splitlines()[-1])
    for step in steps:
        assert step["got"] == step["sent"]
        assert sum(step["worker_tasks"]) == len(step["sent"])
        assert [step["task_worker"].count(w) for w in (0, 1)] == step["worker_tasks"]
    assert sorted(steps[-1]["worker_tasks"]) == [1, 3]


def test_embedded_dask_matches_serial(serial_reference, local_dask):
    result = solve_formation(paper_example(agents=60), local_dask)
    assert_same_run({"status": result.status, "total_cost": result.total_cost,
                     "phi": result.phi, "supersteps": result.supersteps}, serial_reference)
    assert result.workers == 2 and result.backend == "dask"


def test_dask_mpi_matches_serial(serial_reference, tmp_path):
    """mpirun -n 4 --backend dask-mpi: scheduler on rank 0, the run on rank 1, two workers."""
    proc = run_cli("-m", "ocpar.formation", "--backend", "dask-mpi", "--output", str(tmp_path),
                   mpi_ranks=4)
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "dask" and data["workers"] == 2
    assert_same_run(data, serial_reference)
    assert "Dask dashboard: http" in proc.stdout
    assert proc.stderr.strip() == ""


@pytest.mark.slow  # test_matrix runs every scheme on a real external scheduler by default
def test_external_dask_cluster_matches_serial(serial_reference, dask_cluster, tmp_path):
    proc = run_cli("-m", "ocpar.formation", "--backend", "dask", "--scheduler", dask_cluster,
                   "--workers", "2", "--output", str(tmp_path), "--quiet")
    assert proc.returncode == 0, proc.stderr
    data = json.loads((tmp_path / "result.json").read_text())
    assert data["backend"] == "dask" and data["workers"] == 2
    assert_same_run(data, serial_reference)
    # the workers' preload built the formation's inner solver; the run only reused it
    with open_backend("dask", workers=2, scheduler=dask_cluster) as cluster:
        reports = cluster.superstep("ocpar.ocp:cache_report", [None, None])
    assert [r["builds"] for r in reports] == [1, 1]
    assert sum(r["hits"] for r in reports) == data["inner_solves"]


def test_task_dispatch_names_tasks_after_the_run_and_superstep(local_dask):
    """With ``dispatch="tasks"`` the dashboard's task stream shows which run (a job's name)
    and which superstep each chunk belongs to."""
    from distributed import get_task_stream

    from ocpar.bsp.dask import DaskBackend

    scheduler = local_dask.client.scheduler.address
    with DaskBackend(workers=2, scheduler=scheduler, dispatch="tasks",
                     run_name="job-42") as backend, get_task_stream(backend.client) as stream:
        backend.superstep("math:sqrt", [4.0, 9.0, 16.0])
        backend.superstep("math:sqrt", [4.0, 9.0, 16.0])
    keys = {str(task["key"]) for task in stream.data}
    assert {k.split("-superstep-")[1] for k in keys} == {
        "0-round-0-chunk-0", "0-round-0-chunk-1", "1-round-1-chunk-0", "1-round-1-chunk-1"}
    assert all(k.startswith("ocpar-job-42-") for k in keys)


def test_kept_clients_serve_one_run_after_another_and_a_closed_one_is_replaced(
        local_dask, monkeypatch):
    """After ``keep_clients()`` (a warm runner of ocpar serve) runs on one scheduler share one
    client, left open when each ends; one found closed is replaced by a new connection."""
    from ocpar.bsp import dask as dask_backend

    monkeypatch.setattr(dask_backend, "_KEPT", {})
    monkeypatch.setattr(dask_backend, "_keeping", [])
    dask_backend.keep_clients()
    scheduler = local_dask.client.scheduler.address
    clients = []
    try:
        for _ in range(3):
            with open_backend("dask", workers=2, scheduler=scheduler,
                              dispatch="tasks") as backend:
                assert backend.superstep("math:sqrt", [4.0, 9.0]) == [2.0, 3.0]
                clients.append(backend.client)
            assert clients[-1].status == "running"
            if len(clients) == 2:
                clients[-1].close()
        assert clients[0] is clients[1] and clients[2] is not clients[1]
    finally:
        for client in dask_backend._KEPT.values():
            client.close()


def test_the_dashboard_link_a_dask_run_prints_answers(local_dask):
    """The embedded cluster's dashboard (the link every Dask run prints) serves its status
    page, which needs bokeh; without it Dask answers "Dask needs bokeh>=3.1.0"."""
    import httpx

    link = local_dask.dashboard_link
    assert link is not None and link.endswith("/status")
    page = httpx.get(link, timeout=30, follow_redirects=True)
    assert page.status_code == 200, page.text[:200]
    assert "bokeh" in page.text.lower() and "needs bokeh" not in page.text
    tasks = httpx.get(link.replace("/status", "/tasks"), timeout=30)
    assert tasks.status_code == 200
