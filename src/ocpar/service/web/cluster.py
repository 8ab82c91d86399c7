"""The embedded Dask cluster of ``ocpar serve`` (its default backend), as a process of its
own: ``python -m ocpar.service.web.cluster ADDRESS_FILE WORKERS``.

Starts a ``LocalCluster`` of WORKERS single-threaded worker processes on 127.0.0.1 (the
workers' settings of :mod:`ocpar.bsp.dask`), writes the scheduler's address into
ADDRESS_FILE, and runs until it is terminated or the server that started it is gone.
"""

from __future__ import annotations

import os
import signal
import sys
import time
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    import dask
    from distributed import LocalCluster

    from ocpar.bsp.dask import CLUSTER_CONFIG, WORKER_ENV, WORKER_PRELOAD

    address_file, workers = (argv if argv is not None else sys.argv[1:])[:2]
    parent = os.getppid()
    stop = []
    signal.signal(signal.SIGTERM, lambda *_: stop.append(True))
    with dask.config.set(CLUSTER_CONFIG), LocalCluster(
            n_workers=int(workers), threads_per_worker=1, processes=True, host="127.0.0.1",
            scheduler_port=0, dashboard_address=None, env=WORKER_ENV,
            preload=list(WORKER_PRELOAD)) as cluster:
        path = Path(address_file)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(cluster.scheduler_address)
        os.replace(tmp, path)
        while not stop and os.getppid() == parent:  # the server is gone: so is its cluster
            time.sleep(0.5)
    return 0


if __name__ == "__main__":
    sys.exit(main())
