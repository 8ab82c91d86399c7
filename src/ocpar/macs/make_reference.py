"""``python -m ocpar.macs.make_reference --output DIR``: compute the reference Pareto fronts
of the MACS test problems (:mod:`ocpar.macs.reference`) and write them as CSV (by default
over the packaged copies)."""

from __future__ import annotations

import sys
import time
from pathlib import Path

from ocpar.cli import OneLineParser, positive_int
from ocpar.macs import reference
from ocpar.macs.reference import (
    FILES,
    ORBIT_TEST_TF,
    goddard_min_time,
    goddard_reference_front,
    orbit_raising_mesh_refinement,
    orbit_raising_reference_front,
    write_front,
)


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog="ocpar.macs.make_reference",
                           description="Compute the reference Pareto fronts of the MACS test "
                                       "problems and write them as CSV.")
    parser.add_argument("--output", type=Path, default=Path(reference.__file__).parent / "data",
                        help="directory for goddard_front.csv and orbit_raising_front.csv")
    parser.add_argument("--goddard-points", type=positive_int, default=400)
    parser.add_argument("--orbit-points", type=positive_int, default=200)
    args = parser.parse_args(argv)
    if min(args.goddard_points, args.orbit_points) < 2:
        parser.error("a front needs at least 2 points")
    args.output.mkdir(parents=True, exist_ok=True)

    start = time.perf_counter()
    print(f"Goddard: smallest feasible t_f = {goddard_min_time():.12g}")
    goddard = goddard_reference_front(args.goddard_points)
    write_front(args.output / FILES["goddard"], goddard)
    print(f"Goddard: {len(goddard)} points ({time.perf_counter() - start:.1f} s)")

    start = time.perf_counter()
    intervals, table = orbit_raising_mesh_refinement()
    print("orbit raising mesh refinement, E*(t_f) at t_f = "
          + ", ".join(f"{tf:g}" for tf in ORBIT_TEST_TF))
    for k, energies in table:
        print(f"  K = {k:5d}: " + "  ".join(f"{e:.15f}" for e in energies))
    orbit = orbit_raising_reference_front(args.orbit_points, intervals)
    write_front(args.output / FILES["orbit-raising"], orbit)
    print(f"orbit raising: K = {intervals}, {len(orbit)} points "
          f"({time.perf_counter() - start:.1f} s)")
    for name, front in (("goddard", goddard), ("orbit-raising", orbit)):
        lo, hi = front.min(axis=0), front.max(axis=0)
        print(f"{name}: J1 in [{lo[0]:.10g}, {hi[0]:.10g}], J2 in [{lo[1]:.10g}, {hi[1]:.10g}]")
    return 0


if __name__ == "__main__":
    sys.exit(main())
