"""ocpar: large optimal control problems solved as many small, independent ones in parallel.

Layers, imports pointing down only (docs/layout.md's table, checked by tests/test_layering.py):

- interfaces: the command lines (``ocpar.cli``, ``ocpar.driver``, ``ocpar.config``, each
  scheme's ``run``), the job service, the plots;
- ``ocpar.examples``: the papers' problems, built with the public API;
- ``ocpar.formation``, ``ocpar.pursuit``, ``ocpar.macs``: the outer schemes (coordinators);
- ``ocpar.results``, ``ocpar.result_files``: a run's result and its files;
- ``ocpar.ocp``: transcriptions of inner problems into parametric CasADi NLPs;
- ``ocpar.models``: dynamics and costs of the systems;
- ``ocpar.bsp``: the superstep engine and its backends (serial, mpi, dask);
- ``ocpar.options``, ``ocpar.timing``, ...: the foundation.
"""

import os

# ocpar parallelises across processes: each process (coordinator, MPI rank, Dask worker) runs
# one BLAS/OpenMP thread. Measured on 2 cores: two MPI ranks ran at 0.82x of one rank with
# default threading, 1.92x with one thread each. Set these variables before importing ocpar
# to override.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

__version__ = "0.1.0"

#: ``ocpar.load``, ``ocpar.load_trace``, ``ocpar.Run``: a run's files read back, and
#: ``ocpar.by_dimensions`` a Dataset's variables grouped by their dimensions
#: (:mod:`ocpar.result_files`), imported on first use (``import ocpar`` stays light).
__all__ = ["Run", "by_dimensions", "load", "load_trace"]


def __getattr__(name: str) -> object:
    if name in __all__:
        from ocpar import result_files

        return getattr(result_files, name)
    raise AttributeError(f"module 'ocpar' has no attribute {name!r}")
