"""scripts/scaling.py's arithmetic on made-up samples: medians, the fastest 1-worker
baseline, speedups, efficiencies, the two checkouts' ratios, the headline's spread and the
Markdown tables (no runs)."""

from __future__ import annotations

import importlib
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


@pytest.fixture
def scaling(monkeypatch):
    monkeypatch.syspath_prepend(str(SCRIPTS))
    return importlib.import_module("scaling")


def sample(checkout: str, name: str, workers: int, solve: float, process: float,
           cost: float = 1.5, rep: int = 0) -> dict:
    backend = name.split("x")[0]
    return {"rep": rep, "size": "60", "configuration": name, "backend": backend,
            "workers": workers, "checkout": checkout, "process_s": process, "solve_s": solve,
            "process_peak_rss_mb": 100.0 + workers, "worker_peak_rss_mb": [50.0] * workers,
            "timings": None if checkout == "other" else
            {"startup_s": 0.5, "solve_s": solve, "total_s": process - 0.25},
            "supersteps": 7, "inner_solves": 300, "busiest_worker_s": solve / workers,
            "overhead_s": 0.01, "overhead_median_s": 0.001, "trace_wall_s": solve,
            "headline_key": "total_cost", "headline": cost, "headline_hex": cost.hex(),
            "load_1min": 1.0}


def test_medians_baseline_speedups_ratios(scaling):
    size = scaling.Size("60", "60", ("--agents", "60"), 60)
    configs = {"60": scaling.configurations(["serial", "mpi"], [1, 2])}
    checkouts = [scaling.Checkout("this", Path("/a"), "aaaaaaa", "a" * 40, False),
                 scaling.Checkout("other", Path("/b"), "bbbbbbb", "b" * 40, False)]
    samples = []
    for rep, (s1, m1, m2) in enumerate([(1.0, 0.8, 0.5), (1.2, 0.9, 0.4), (1.1, 3.0, 0.45)]):
        # this: mpi x1 (median 0.9) is the fastest 1-worker solve; serial's whole process
        # (median 3.1 s) the fastest 1-worker process
        samples += [sample("this", "serial", 1, s1, 3.0 + s1 - 1.0, rep=rep),
                    sample("this", "mpix1", 1, m1, 4.0, rep=rep),
                    sample("this", "mpix2", 2, m2, 3.5, rep=rep),
                    sample("other", "serial", 1, 2 * s1, 6.0, rep=rep),
                    sample("other", "mpix1", 1, 2 * m1, 8.0, rep=rep),
                    sample("other", "mpix2", 2, 2 * m2, 7.0, rep=rep)]
    sizes = scaling.summaries(samples, [size], configs, checkouts)
    entry = sizes["60"]
    this = entry["configurations"]["this"]
    assert this["serial"]["solve_s"] == pytest.approx(1.1)
    assert this["mpix1"]["solve_s"] == pytest.approx(0.9)
    assert this["mpix2"]["solve_s"] == pytest.approx(0.45)
    assert entry["baseline"]["solve"] == {"checkout": "this", "configuration": "mpix1",
                                          "s": pytest.approx(0.9)}
    assert entry["baseline"]["process"]["configuration"] == "serial"
    assert entry["baseline"]["process"]["s"] == pytest.approx(3.1)
    assert this["mpix2"]["solve_speedup"] == pytest.approx(0.9 / 0.45)
    assert this["mpix2"]["solve_efficiency"] == pytest.approx(0.9 / 0.45 / 2)
    assert this["mpix2"]["process_speedup"] == pytest.approx(3.1 / 3.5)
    # the other checkout against the same (fastest) baseline
    other = entry["configurations"]["other"]
    assert other["mpix2"]["solve_speedup"] == pytest.approx(0.9 / 0.9)
    assert entry["other_over_this"]["mpix2"]["solve_s"] == pytest.approx(2.0)
    assert entry["other_over_this"]["serial"]["process_s"] == pytest.approx(6.0 / 3.1)
    assert this["serial"]["timings"]["startup_s"] == 0.5
    assert this["serial"]["outside_s"] == pytest.approx(0.25)
    assert other["serial"]["timings"] is None
    assert this["mpix2"]["worker_peak_rss_mb"] == [50.0, 50.0]
    assert entry["headline"]["this"]["identical_bits"]
    assert entry["headline_same_across_checkouts"]

    report = {"scheme": "formation", "sizes": sizes,
              "checkouts": {"this": {"label": "aaaaaaa"}, "other": {"label": "bbbbbbb"}},
              "configurations": {"60": [{"backend": c.backend, "workers": c.workers}
                                        for c in configs["60"]]}}
    entry["key"] = "60"
    tables = scaling.markdown(report)
    assert "| agents | backend | P = 1 | 2 |" in tables
    assert "| 60 | mpi @aaaaaaa | 0.9 s (1.00×) | 0.45 s (2.00×) |" in tables
    assert "| 60 | serial @aaaaaaa | 1.1 s (0.82×) |  |" in tables
    assert "| 60 | mpi | 2.00× / 2.00× | 2.00× / 2.00× |" in tables


def test_headline_spread(scaling):
    spread = scaling.headline_spread([sample("this", "serial", 1, 1.0, 2.0, cost=1.0),
                                      sample("this", "mpix2", 2, 1.0, 2.0, cost=1.0 + 2e-16),
                                      sample("this", "mpix1", 1, 1.0, 2.0, cost=1.0)])
    assert not spread["identical_bits"]
    assert spread["values"] == {(1.0).hex(): 2, (1.0 + 2e-16).hex(): 1}
    assert spread["relative_spread"] == pytest.approx(2.220446049250313e-16)
