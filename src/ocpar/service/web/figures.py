"""The plots of ``ocpar serve``'s jobs, drawn when first asked for, not in the job.

A job on a warm runner (:mod:`ocpar.service.web.warm`) writes its result files but no plots:
it keeps its result (``picture.pickle``) and the names of its plots (``picture.json``) in its
directory, so its time excludes drawing. The first ``GET`` of one of those plots has the
server's drawing runner (:attr:`~ocpar.service.web.warm.WarmPool.drawer`, warm: Matplotlib
imported) draw them all into the job's ``output/``, where they stay (the cache) and are
served as any output file. Jobs under ``mpirun`` draw their plots themselves.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import threading
import time
from pathlib import Path

from ocpar.service.jobs import run_command
from ocpar.service.web.warm import PICTURE_NAMES, WarmPool

#: Seconds a drawing may take, the drawing runner's start included.
DRAW_TIMEOUT_S = 120.0


class DrawingFailed(RuntimeError):
    """The plots of a job could not be drawn (one line)."""


def pending(path: Path) -> list[str]:
    """The plots of the job in ``path`` still to be drawn (file names in ``output/``)."""
    try:
        names = json.loads((path / PICTURE_NAMES).read_text())
    except (OSError, ValueError):
        return []
    return [name for name in names if isinstance(name, str)
            and not (path / "output" / name).exists()]


class Figures:
    """Draws the plots of jobs on ``pool``'s drawing runner, one job at a time."""

    def __init__(self, pool: WarmPool | None) -> None:
        self.pool = pool
        self._lock = threading.Lock()

    def draw(self, path: Path, scheme: str, argv: list[str]) -> None:
        """Draw the pending plots of the job in ``path`` (its scheme and command line);
        DrawingFailed if the drawing runner fails or takes over :data:`DRAW_TIMEOUT_S`."""
        deadline = time.monotonic() + DRAW_TIMEOUT_S
        with self._lock:
            if not pending(path):
                return  # drawn meanwhile
            if self.pool is None:
                raise DrawingFailed("this server has no drawing runner")
            while (drawer := self.pool.drawer) is None or not drawer.idle:
                if time.monotonic() > deadline:
                    raise DrawingFailed("the drawing runner did not start")
                time.sleep(0.02)
            job = drawer.run(path, run_command(path, scheme, argv, []), draw=True)
            while (code := job.poll()) is None:
                if time.monotonic() > deadline:  # the pool starts another drawing runner
                    with contextlib.suppress(ProcessLookupError, PermissionError):
                        os.killpg(drawer.proc.pid, signal.SIGKILL)
                    drawer.proc.wait()
                    job.poll()
                    raise DrawingFailed(f"drawing took over {DRAW_TIMEOUT_S:g} s")
                time.sleep(0.01)
        if code != 0 or pending(path):
            raise DrawingFailed(f"drawing failed (status {code}; see runners.log in the "
                                "server's state directory)")
