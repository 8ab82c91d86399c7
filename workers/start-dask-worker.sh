#!/usr/bin/env bash
# Start Dask worker processes for ocpar on this host: one thread per process (IPOPT/MUMPS is
# not thread-safe), one BLAS/OpenMP thread, solver cache warmed by the preload.
#   workers/start-dask-worker.sh tcp://SCHEDULER:8786 [NPROCS]   (NPROCS default: all cores)
set -euo pipefail
scheduler=${1:?usage: $0 tcp://SCHEDULER:8786 [NPROCS]}
nprocs=${2:-$(nproc)}
here=$(cd "$(dirname "$0")" && pwd)
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
export DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False
exec dask worker "$scheduler" --nworkers "$nprocs" --nthreads 1 --no-dashboard \
    --preload "$here/ocpar_preload.py"
