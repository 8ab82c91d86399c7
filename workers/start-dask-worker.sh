#!/usr/bin/env bash
# Start Dask worker processes for ocpar on this host: one thread per process (IPOPT/MUMPS is
# not thread-safe), one BLAS/OpenMP thread, solver cache warmed by the preload.
#   workers/start-dask-worker.sh tcp://SCHEDULER:8786 [NPROCS]   (NPROCS default: all cores)
# TLS (a scheduler started with --protocol tls, see workers/tls.md): set all three of
#   OCPAR_TLS_CA_FILE  CA certificate (PEM) that signed the scheduler's and clients' certificates
#   OCPAR_TLS_CERT     this host's worker certificate (PEM), signed by that CA
#   OCPAR_TLS_KEY      its private key (PEM, unencrypted)
# and give a tls:// address; they are passed on as dask worker --tls-ca-file/--tls-cert/--tls-key:
#   OCPAR_TLS_CA_FILE=ca.pem OCPAR_TLS_CERT=worker.pem OCPAR_TLS_KEY=worker.key \
#       workers/start-dask-worker.sh tls://SCHEDULER:8786 4
set -euo pipefail
usage="usage: $0 tcp://SCHEDULER:8786|tls://SCHEDULER:8786 [NPROCS]"
scheduler=${1:?$usage}
nprocs=${2:-$(nproc)}
here=$(cd "$(dirname "$0")" && pwd)

die() { echo "$0: error: $*" >&2; exit 2; }

tls=()
if [[ -n ${OCPAR_TLS_CA_FILE:-} || -n ${OCPAR_TLS_CERT:-} || -n ${OCPAR_TLS_KEY:-} ]]; then
    for var in OCPAR_TLS_CA_FILE OCPAR_TLS_CERT OCPAR_TLS_KEY; do
        path=${!var:-}
        [[ -n $path ]] ||
            die "OCPAR_TLS_CA_FILE, OCPAR_TLS_CERT and OCPAR_TLS_KEY go together: $var is not set"
        [[ -f $path && -r $path ]] || die "$var=$path is not a readable file"
    done
    [[ $scheduler == tls://* ]] ||
        die "TLS certificates need a tls:// scheduler address, got $scheduler"
    tls=(--tls-ca-file "$OCPAR_TLS_CA_FILE" --tls-cert "$OCPAR_TLS_CERT"
         --tls-key "$OCPAR_TLS_KEY")
fi

export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
export DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED=False
exec dask worker "$scheduler" --nworkers "$nprocs" --nthreads 1 --no-dashboard \
    --preload "$here/ocpar_preload.py" ${tls[@]+"${tls[@]}"}
