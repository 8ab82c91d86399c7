#!/usr/bin/env python
"""Where a formation picture's time goes, in a warm process (Matplotlib already imported).

    python scripts/picture_bench.py --agents 60 2000 100000 --repeats 3 --output DIR

For each fleet size: the point-mass paper example solved once serially, then
``ocpar.formation.plot.plot_formation`` drawn ``--repeats`` times into DIR; per draw the
seconds of setting up the figure and its artists (everything before the render), of the
render (constrained layout and rasterisation: one ``canvas.draw``) and of writing the PNG,
and the medians. The first figure is the cold import of Matplotlib (the process's own
cost, paid once). Writes ``picture_bench.json`` into DIR. With another checkout's ``src`` on
PYTHONPATH it measures that code (there ``render_s`` may include the PNG write).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

import ocpar.formation.plot
import ocpar.plotting
from ocpar.examples import formation_point_masses
from ocpar.formation import solve_formation


def timed_draw(problem, result, path: Path) -> dict[str, float]:
    """One ``plot_formation`` call split into set-up, render and PNG write (seconds)."""
    marks: dict[str, float] = {}
    save = ocpar.plotting.save

    def timing_save(fig, target):
        marks["setup_end"] = time.perf_counter()
        draw = fig.canvas.draw

        def timing_draw():
            draw()
            marks["render_end"] = time.perf_counter()

        fig.canvas.draw = timing_draw
        return save(fig, target)

    ocpar.formation.plot.save = timing_save
    try:
        start, cpu = time.perf_counter(), time.process_time()
        ocpar.formation.plot.plot_formation(problem, result, path)
        end, cpu = time.perf_counter(), time.process_time() - cpu
    finally:
        ocpar.formation.plot.save = save
    # older code (``savefig``) renders without calling canvas.draw: render and PNG as one
    render_end = marks.get("render_end", end)
    return {"total_s": end - start, "cpu_s": cpu, "setup_s": marks["setup_end"] - start,
            "render_s": render_end - marks["setup_end"], "png_s": end - render_end}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[60, 2000, 100_000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    start, cpu = time.perf_counter(), time.process_time()
    from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: F401
    from matplotlib.figure import Figure  # noqa: F401
    report: dict = {"matplotlib_import_s": time.perf_counter() - start,
                    "matplotlib_import_cpu_s": time.process_time() - cpu, "sizes": []}
    for agents in args.agents:
        problem = formation_point_masses.make(agents=agents)
        solving = time.perf_counter()
        result = solve_formation(problem)
        solve_s = time.perf_counter() - solving
        path = args.output / f"formation-{agents}.png"
        draws = [timed_draw(problem, result, path) for _ in range(args.repeats)]
        median = {key: float(np.median([d[key] for d in draws])) for key in draws[0]}
        report["sizes"].append({"agents": agents, "status": result.status, "solve_s": solve_s,
                                "median": median, "draws": draws,
                                "png_bytes": path.stat().st_size})
        print(f"{agents} agents: picture {median['total_s']:.3f} s, CPU {median['cpu_s']:.3f} s "
              f"(set-up "
              f"{median['setup_s']:.3f}, render {median['render_s']:.3f}, PNG "
              f"{median['png_s']:.3f}); solve {solve_s:.2f} s", flush=True)
    (args.output / "picture_bench.json").write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
