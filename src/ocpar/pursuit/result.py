"""The result of a pursuit run, as an object and as ``result.json``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ocpar.results import RunResult


@dataclass
class PursuitResult(RunResult):
    """Outcome of :func:`ocpar.pursuit.solve_pursuit`.

    Masses in kg, times in s; ``x`` (N, 4) and ``u`` (N−1, 2) are the result trajectory;
    ``initial_x`` agent 0's; ``reference_x`` the full-horizon MS solution when computed.
    """

    scheme: ClassVar[str] = "pursuit"

    case: int
    samples: int
    mode: str
    window: int
    update: int
    epsilon_kg: float
    final_mass_kg: float
    fuel_kg: float
    agents: int
    subproblem_solves: int
    max_agents_in_flight: int
    constraint_violation: float
    rk_final_altitude_error_m: float
    rk_final_radial_velocity_mps: float
    rk_final_position_error_m: float
    x: np.ndarray
    u: np.ndarray
    initial_x: np.ndarray
    final_masses_kg: list[float] = field(default_factory=list)
    reference_final_mass_kg: float | None = None
    reference_x: np.ndarray | None = None
    #: the common count of inner solves is the catch-up (and full-horizon) solves
    inner_solves: int = field(init=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        self.inner_solves = self.subproblem_solves

    @property
    def peak_rss_mb_per_worker(self) -> float:
        """Largest peak resident memory of any worker process during the run (MiB)."""
        return max((m for t in self.trace for m in t.worker_peak_rss_mb), default=0.0)

    def scheme_fields(self) -> dict:
        """Pursuit's fields of ``result.json``, with trajectories and per-agent final masses."""
        return {
            "case": self.case,
            "samples": self.samples,
            "mode": self.mode,
            "window": self.window,
            "update": self.update,
            "epsilon_kg": self.epsilon_kg,
            "final_mass_kg": self.final_mass_kg,
            "fuel_kg": self.fuel_kg,
            "agents": self.agents,
            "subproblem_solves": self.subproblem_solves,
            "max_agents_in_flight": self.max_agents_in_flight,
            "constraint_violation": self.constraint_violation,
            "rk_final_altitude_error_m": self.rk_final_altitude_error_m,
            "rk_final_radial_velocity_mps": self.rk_final_radial_velocity_mps,
            "rk_final_position_error_m": self.rk_final_position_error_m,
            "peak_rss_mb_per_worker": self.peak_rss_mb_per_worker,
            "reference_ms_final_mass_kg": self.reference_final_mass_kg,
            "final_masses_kg": self.final_masses_kg,
            "states": np.asarray(self.x).tolist(),
            "controls": np.asarray(self.u).tolist(),
        }

    def summary(self) -> str:
        ref = ("" if self.reference_final_mass_kg is None
               else f"   (full-horizon MS: {self.reference_final_mass_kg:.6f} kg)")
        return (
            f"status {self.status} ({self.message})\n"
            f"final mass {self.final_mass_kg:.6f} kg, fuel {self.fuel_kg:.6f} kg{ref}\n"
            f"agents {self.agents}   subproblem solves {self.subproblem_solves} "
            f"(failed {self.failed_solves}, retries {self.retries})   "
            f"supersteps {self.supersteps}   "
            f"max in flight {self.max_agents_in_flight}\n"
            f"constraint violation {self.constraint_violation:.1e}   RK re-simulation: "
            f"altitude error {self.rk_final_altitude_error_m / 1e3:.2f} km, radial velocity "
            f"{self.rk_final_radial_velocity_mps:.2f} m/s\n"
            f"wall time {self.wall_time_s:.2f} s on {self.workers} {self.backend} worker(s), "
            f"peak memory per worker {self.peak_rss_mb_per_worker:.0f} MiB"
        )
