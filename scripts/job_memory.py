"""Peak memory (the largest process's resident set) of each scheme's serial run against its
problem size, for the memory estimates of ``ocpar serve`` (:mod:`ocpar.service.web.memory`);
writes JSON.

::

    python scripts/job_memory.py --output memory.json

Each run is ``python -m ocpar.<scheme> ... --backend serial`` (one process holds every agent:
an upper bound for one process of a distributed run) with its output in a temporary
directory; its peak is ``ru_maxrss`` of that process (``os.wait4``).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

#: (scheme, size key, sizes, other options)
RUNS = [
    ("formation", "agents", [2, 10_000, 40_000], []),
    ("pursuit", "samples", [301, 1_201, 2_401], ["--no-reference"]),
    ("macs", "max_evals", [100, 2_000, 8_000], []),
]


def peak_rss(argv: list[str], cwd: Path) -> tuple[float, float]:
    """(peak resident set in MB, seconds) of ``python -m argv`` in ``cwd``."""
    env = dict(os.environ, OMP_NUM_THREADS="1")
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, "-m", *argv], cwd=cwd, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode not in (0, 1):
        raise RuntimeError(f"{' '.join(argv)}: exit status {proc.returncode}")
    return usage.ru_maxrss / 1024, time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output", required=True, help="the JSON report")
    args = parser.parse_args(argv)
    report = []
    with tempfile.TemporaryDirectory() as tmp:
        for scheme, key, sizes, options in RUNS:
            for size in sizes:
                flag = "--" + key.replace("_", "-")
                mb, seconds = peak_rss([f"ocpar.{scheme}", flag, str(size), *options,
                                        "--backend", "serial", "--output",
                                        f"{tmp}/{scheme}-{size}"], Path(tmp))
                entry = {"scheme": scheme, key: size, "options": options,
                         "peak_rss_mb": round(mb, 1), "seconds": round(seconds, 1)}
                print(json.dumps(entry), flush=True)
                report.append(entry)
    Path(args.output).write_text(json.dumps(report, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
