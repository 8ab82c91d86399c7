"""The formation paper's second example (§II, §VI, Fig. 5): rigid spacecraft near the
Sun–Earth L2 halo.

Relative coordinates about the halo (the paper's Remark 2): positions in km from the halo
point, time in the normalised unit of the three-body problem (1 year / 2π ≈ 58.1 days), the
dynamics linearised about the halo
(:class:`~ocpar.models.rigid_spacecraft.RelativeRigidSpacecraft`).
The manoeuvre starts at the halo's crossing of the x1–x3 plane (its initial state) and lasts
``duration`` time units.

* Start: a grid of 6 columns (along x1) and as many rows (along x2) as needed, 200 m apart,
  centred on the halo point in the x1–x2 plane (6 × 5 for 30 spacecraft), at rest relative to
  the halo, attitude p = (cos π/2, sin π/2 · (1, 0, 0)) (a rotation by π about x1).
* End: equidistant on the circle of radius 1 km about the halo point in the plane with normal
  (1, 0, 1)/√2 (all three position components fixed on the circle, so the spacecraft are
  coplanar), at rest relative to the halo, p = (−1, 0, 0, 0) as the paper prints it
  (cos π, sin π · (0, 1, 0)): a rotation by 2π, the same attitude as the identity. The signed
  quaternion is kept, so each spacecraft turns from p_0 to −1 (a rotation by π).
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from ocpar.formation import Circle, DmocShape, FormationProblem
from ocpar.models import HaloOrbit, RelativeRigidSpacecraft, halo_orbit

GRID_SPACING_KM = 0.2
GRID_COLUMNS = 6
START_ATTITUDE = np.array([0.0, 1.0, 0.0, 0.0])
FINAL_ATTITUDE = np.array([-1.0, 0.0, 0.0, 0.0])
PLANE_NORMAL = np.array([1.0, 0.0, 1.0]) / math.sqrt(2.0)
#: In-plane axes of the final circle: x2, and the normal × x2.
PLANE_AXES = np.array([[0.0, 1.0, 0.0], np.cross(PLANE_NORMAL, [0.0, 1.0, 0.0])])


@lru_cache(maxsize=1)
def default_halo() -> HaloOrbit:
    """The L2 halo of the example (Richardson amplitude 205,000 km, max z ≈ 227,900 km), once per
    process."""
    return halo_orbit()


def grid_positions(agents: int, spacing_km: float = GRID_SPACING_KM) -> np.ndarray:
    """Start positions (agents, 3) km: rows of :data:`GRID_COLUMNS` along x1, stacked along x2,
    centred on the origin, x3 = 0."""
    rows = math.ceil(agents / GRID_COLUMNS)
    columns = min(agents, GRID_COLUMNS)
    k = np.arange(agents)
    x1 = (k % GRID_COLUMNS - (columns - 1) / 2) * spacing_km
    x2 = (k // GRID_COLUMNS - (rows - 1) / 2) * spacing_km
    return np.column_stack([x1, x2, np.zeros(agents)])


def make(
    agents: int = 30,
    radius_km: float = 1.0,
    intervals: int = 10,
    duration: float = 1.0,
    halo: HaloOrbit | None = None,
) -> FormationProblem:
    """The example above: ``agents`` rigid spacecraft, circle radius ``radius_km``, DMOC with
    ``intervals`` intervals over ``duration`` normalised time units, about ``halo`` (default
    :func:`default_halo`)."""
    if agents < 2:  # checked before the halo's integration
        raise ValueError(f"a formation needs at least 2 agents, got {agents}")
    if not (intervals >= 1 and duration > 0):
        raise ValueError("intervals must be ≥ 1 and duration > 0")
    halo = halo or default_halo()
    midpoints = (np.arange(intervals) + 0.5) * duration / intervals
    model = RelativeRigidSpacecraft.from_matrices(halo.potential_hessians(midpoints))
    starts = np.hstack([grid_positions(agents), np.tile(START_ATTITUDE, (agents, 1))])
    return FormationProblem(
        name="crtbp-rigid",
        shape=DmocShape(model, intervals, duration),
        curve=Circle(radius=radius_km, center=np.zeros(3), axes=PLANE_AXES),
        starts=starts,
        final_attitude=FINAL_ATTITUDE,
    )
