#!/usr/bin/env python
"""PBMS's reported improvement still to come at the stop against what is actually left.

    python scripts/pursuit_remaining.py --output runs/pursuit-remaining
    python scripts/pursuit_remaining.py --problems vdp pendulum --extrapolated

Each problem (``--problems``: the paper's case 1, N = 301, and case 2, N = 501, both N_Δ = 60,
N_δ = 32; the pendulum of docs/tutorials/pursuit.md, its code taken from the tutorial's text;
the van der Pol example, N = 41, N_Δ = 21, N_δ = 10, and on the issue's grid, Euler, N = 300,
N_Δ = 31, N_δ = 15, at most 20,000 agents) runs serially with each of its ε (the default 1e-3
and ten times smaller; the pendulum also with the tutorial's 1e-6 and 1e-7), with the
full-horizon MS reference: the reported remaining
improvement of the headline (``estimated_remaining``), how it was obtained, the actual
remaining (the headline's distance to the reference), their ratio, agents, the stop reason and
the wall time. ``--extrapolated`` also runs each with ``certify_samples=0`` (the extrapolated
estimate alone, the rule before the certificate). Writes ``pursuit_remaining.json`` and
prints a Markdown table.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import re
import sys
import tempfile
from pathlib import Path

from ocpar.pursuit import PursuitProblem, PursuitSettings, solve_pursuit

TUTORIAL = Path(__file__).resolve().parents[1] / "docs" / "tutorials" / "pursuit.md"
#: problem: (N_Δ, N_δ, the ε values, max_agents)
RUNS = {"case1": (60, 32, (1e-3, 1e-4), 100_000), "case2": (60, 32, (1e-3, 1e-4), 100_000),
        "pendulum": (21, 10, (1e-3, 1e-4, 1e-6, 1e-7), 100_000),
        "vdp": (21, 10, (1e-3, 1e-4), 100_000), "vdp-euler300": (31, 15, (1e-3, 1e-4), 20_000)}


def tutorial_pendulum(workdir: Path) -> PursuitProblem:
    """The tutorial's ``mytut.pursuit:make()``, written from the tutorial's first code block
    into ``workdir`` as a user would."""
    code = re.findall(r"```python\n(.*?)```", TUTORIAL.read_text(), re.S)[0]
    package = workdir / "mytut"
    package.mkdir(exist_ok=True)
    (package / "__init__.py").write_text("")
    (package / "pursuit.py").write_text(code)
    sys.path.insert(0, str(workdir))
    from mytut.pursuit import make  # type: ignore[import-not-found]

    return make()


def build(name: str, workdir: Path) -> PursuitProblem:
    from ocpar.examples import pursuit_orbit_transfer, pursuit_van_der_pol

    if name == "pendulum":
        return tutorial_pendulum(workdir)
    if name == "vdp":
        return pursuit_van_der_pol.make()
    if name == "vdp-euler300":
        return pursuit_van_der_pol.make(samples=300, integrator="euler")
    case = int(name[-1])
    return pursuit_orbit_transfer.make(case=case, samples={1: 301, 2: 501}[case])


def measure(problem: PursuitProblem, settings: PursuitSettings) -> dict:
    result = solve_pursuit(problem, settings)
    # the paper's train (finish="train"): its own last headline and what it reported left
    actual = problem.improvement(result.train_headline, result.reference_headline)
    reported = result.train_remaining
    return {"problem": problem.name, "samples": problem.samples, "epsilon": settings.epsilon,
            "certify_samples": settings.certify_samples, "reported": reported,
            "method": result.train_remaining_method, "actual": actual,
            "ratio": actual / reported if reported else None, "agents": result.agents,
            "stop_reason": result.stop_reason, "headline": result.train_headline,
            "reference": result.reference_headline, "certificate": result.certificate_headline,
            "solves": result.subproblem_solves,
            "wall_s": result.wall_time_s}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", nargs="+", choices=sorted(RUNS), default=list(RUNS))
    parser.add_argument("--extrapolated", action="store_true",
                        help="also run each with certify_samples=0")
    parser.add_argument("--output", type=Path, default=Path("runs/pursuit-remaining"))
    args = parser.parse_args()
    args.output.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as workdir:
        for name in args.problems:
            window, update, epsilons, max_agents = RUNS[name]
            problem = build(name, Path(workdir))
            for epsilon in epsilons:
                settings = PursuitSettings(window=window, update=update, epsilon=epsilon,
                                           max_agents=max_agents, finish="train")
                variants = [settings] + ([dataclasses.replace(settings, certify_samples=0)]
                                         if args.extrapolated else [])
                for variant in variants:
                    rows.append(measure(problem, variant))
                    row = rows[-1]
                    print(f"| {name} | {epsilon:g} | {row['reported']:.3g} ({row['method']}) | "
                          f"{row['actual']:.3g} | "
                          f"{'-' if row['ratio'] is None else format(row['ratio'], '.3f')} | "
                          f"{row['agents']} | {row['stop_reason']} | {row['wall_s']:.1f} s |",
                          flush=True)
    (args.output / "pursuit_remaining.json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
