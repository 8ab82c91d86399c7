"""A CasADi Function compiled to machine code by the host's C compiler, built once per host
and cached on disk by content, and evaluated on many points.

CasADi's virtual machine spends a few ns per instruction per point, as numpy does over many
points (:mod:`ocpar.ocp.columns_eval`); its generated C (``CodeGenerator``) compiled with
``-O2`` evaluated a unicycle's RK4 stage derivatives (344 instructions) in 85 ns per point
(190 ns with the blocks' transposes to and from rows of entries) against 500 ns by numpy
(CPU time, 50,000 points, this machine, 2026-12); building one costs seconds, once per host
(:data:`FLAGS`). The shared
library is named by a hash of the generated source, the compiler command and CasADi's
version, built by one process while the others that need it wait on a lock file beside it
(MPI ranks or Dask workers of one host compile it once between them; a later run not at
all), written under a temporary name and renamed into place, then loaded with
``casadi.external``. The cache is ``$OCPAR_CACHE/compiled``
(default ``~/.cache/ocpar/compiled``); the compiler ``$CC`` (default ``cc``). The compiled
code keeps IEEE arithmetic (``-ffp-contract=off``, no fast-math) and CasADi's generated C does
the virtual machine's operations in its order, so its results are the virtual machine's bit
for bit (tested per kernel). Where the host has no compiler, or compiling fails, the process
says so in one line on stderr (once per compiler and reason) and evaluates on the virtual
machine.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from functools import cache, lru_cache
from pathlib import Path

import casadi as ca
import numpy as np

#: Points per call of a compiled map: 256 ran faster than 2048.
BLOCK = 256
#: The compiler's flags: -O1 (a unicycle's N = 20 Newton step: 4.5 s to build against 19.6 s
#: at -O2, and 5 % slower), IEEE arithmetic (no contraction into FMA, no fast-math).
FLAGS = ("-O1", "-fPIC", "-shared", "-ffp-contract=off")


def cache_directory() -> Path:
    """Where compiled functions are kept: ``$OCPAR_CACHE/compiled`` (default
    ``~/.cache/ocpar/compiled``)."""
    root = os.environ.get("OCPAR_CACHE") or Path.home() / ".cache" / "ocpar"
    return Path(root) / "compiled"


#: The environment variable that turns compiling off (``0``): every inner function then runs
#: on CasADi's virtual machine, with the same bits, slower, and no run waits for a compiler
#: (e.g. many short runs of shapes the cache has not seen: the test suite sets it).
COMPILE_ENV = "OCPAR_COMPILE"


def compiled(function: ca.Function) -> ca.Function | None:
    """``function`` compiled (module docstring), or None where compiling is turned off
    (:data:`COMPILE_ENV` ``0``), this host has no C compiler (``$CC``, else ``cc``) or the
    compilation fails: the caller then evaluates it as it is."""
    if os.environ.get(COMPILE_ENV) == "0":
        return None
    return _compiled(function)


@lru_cache(maxsize=32)
def _compiled(function: ca.Function) -> ca.Function | None:
    """:func:`compiled` where compiling is on."""
    command = os.environ.get("CC", "cc")
    compiler = shutil.which(command)
    if compiler is None:
        _say_once(f"ocpar: no C compiler ({command!r} not found): inner functions run on "
                  "CasADi's virtual machine")
        return None
    name = function.name()
    generator = ca.CodeGenerator(f"{name}.c", {"with_header": False})
    generator.add(function)
    source = generator.dump()
    key = hashlib.sha256("\n".join([source, compiler, *FLAGS, ca.__version__]).encode()
                         ).hexdigest()[:20]
    directory = cache_directory()
    library = directory / f"{name}_{key}.so"
    if not library.exists():
        try:
            directory.mkdir(parents=True, exist_ok=True)
            with open(directory / f"{name}_{key}.lock", "w") as lock:
                fcntl.flock(lock, fcntl.LOCK_EX)    # the others wait, then find the library
                if not library.exists():
                    _compile(compiler, source, name, library)
        except (OSError, subprocess.SubprocessError) as error:
            _say_once(f"ocpar: compiling with {compiler} failed ({type(error).__name__}): "
                      "inner functions run on CasADi's virtual machine")
            return None
    return ca.external(name, str(library))


def _compile(compiler: str, source: str, name: str, library: Path) -> None:
    """``source`` compiled by ``compiler`` into a temporary file renamed to ``library``."""
    with tempfile.TemporaryDirectory(dir=library.parent) as tmp:
        c_file, built = Path(tmp) / f"{name}.c", Path(tmp) / f"{name}.so"
        c_file.write_text(source)
        subprocess.run([compiler, *FLAGS, str(c_file), "-o", str(built)], check=True,
                       capture_output=True, timeout=300)
        os.replace(built, library)


@cache
def _say_once(line: str) -> None:
    """``line`` on stderr, once per process."""
    print(line, file=sys.stderr)


class CompiledPoints:
    """``function`` (dense column inputs, dense outputs) compiled and mapped over
    :data:`BLOCK` points, called on any number of points through its own buffers, each
    entry's values over the points a row (the blocks transposed to and from the map's
    point-after-point buffers while they are in cache). Each point's outputs are those of the
    function at that point alone."""

    def __init__(self, mapped: ca.Function) -> None:
        self._name = mapped.name()
        self._buffer, self._evaluate = mapped.buffer()
        self._inputs = [np.zeros((BLOCK, mapped.nnz_in(i) // BLOCK))
                        for i in range(mapped.n_in())]
        self._outputs = [np.zeros((BLOCK, mapped.nnz_out(i) // BLOCK))
                         for i in range(mapped.n_out())]
        for i, array in enumerate(self._inputs):
            self._buffer.set_arg(i, memoryview(array))
        for i, array in enumerate(self._outputs):
            self._buffer.set_res(i, memoryview(array))

    @classmethod
    def of(cls, function: ca.Function) -> CompiledPoints | None:
        """The compiled evaluation of ``function``, None where it cannot be compiled."""
        mapped = compiled(function.map(BLOCK, "serial"))
        return None if mapped is None else cls(mapped)

    def __call__(self, *rows: np.ndarray) -> list[np.ndarray]:
        """The outputs (size, m) at m points given as one (size, m) array per input (each
        entry's values over the points a row, entries column-major)."""
        m = rows[0].shape[1]
        outputs = [np.empty((array.shape[1], m)) for array in self._outputs]
        for start in range(0, m, BLOCK):
            block = slice(start, min(start + BLOCK, m))
            count = block.stop - start
            for array, row in zip(self._inputs, rows, strict=True):
                array[:count] = row[:, block].T     # the rest: the last block's points
            self._evaluate()
            if self._buffer.ret():
                raise RuntimeError(f"{self._name}: evaluation failed")
            for out, array in zip(outputs, self._outputs, strict=True):
                out[:, block] = array[:count].T
        return outputs
