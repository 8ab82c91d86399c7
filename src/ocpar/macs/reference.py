"""Reference Pareto fronts of the MACS paper's two bi-objective test problems (§V).

Both fronts are computed, not tabulated: one single-objective optimal control problem per final
time t_f (t_0 = 0), the front being the curve of those optima, rows (J1, J2) = (t_f, J2*(t_f)).

* Goddard-like ascent (eqs. 16–18): g = 1.6e-3, a = 4e-3, h = 10. For fixed t_f the maximum of
  v_x(t_f) under y(t_f) = h, v_y(t_f) = 0 follows the linear tangent law tan u = c1 + c2 t
  (Bryson & Ho): λ_x = 0, λ_vx = −1 and λ_vy linear in t. The constants are found by shooting
  (accurate integration and a root finder), continued along the t_f grid.
* Maximum-energy orbit raising (eqs. 19–21): a = 1e-2. For fixed t_f the maximum final specific
  energy E = (v_r² + v_t²)/2 − 1/r comes from a Hermite–Simpson transcription solved by IPOPT
  with exact derivatives, mesh-refined, continued along the t_f grid.

``python -m ocpar.macs.make_reference --output DIR`` writes both fronts as CSV; the packaged
copies are read by :func:`reference_front`.
"""

from __future__ import annotations

from functools import lru_cache
from importlib import resources
from pathlib import Path

import casadi as ca
import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import root

from ocpar.ocp.ipopt import ipopt_options

GODDARD_G = 1.6e-3
GODDARD_A = 4e-3
GODDARD_H = 10.0
GODDARD_TF_MAX = 250.0
ORBIT_A = 1e-2
ORBIT_X0 = np.array([1.1, 0.0, 0.0, 1.0 / np.sqrt(1.1)])
ORBIT_TF = (20.0, 80.0)
#: final times at which the orbit-raising mesh is refined
ORBIT_TEST_TF = (20.0, 50.0, 80.0)
FILES = {"goddard": "goddard_front.csv", "orbit-raising": "orbit_raising_front.csv"}
_SHOOTING_RTOL = 1e-12
_RESIDUAL_TOL = 1e-11


# --- Goddard-like ascent ---------------------------------------------------------------------

def goddard_min_time() -> float:
    """Smallest feasible t_f (time units) of the ascent: the minimum-time solution.

    With v_x(t_f) free, λ_vx = 0, so u is bang-bang: u = π/2 (net acceleration a − g) up to
    t1, then u = −π/2 (−(a + g)) until v_y = 0 at y = h. That gives
    t_f = √(2h (1/(a − g) + 1/(a + g))), and v_x(t_f) = 0 there.
    """
    g, a, h = GODDARD_G, GODDARD_A, GODDARD_H
    return float(np.sqrt(2.0 * h * (1.0 / (a - g) + 1.0 / (a + g))))


def _goddard_final_state(angles: np.ndarray, tf: float) -> np.ndarray:
    """State (x, v_x, y, v_y) at t_f under tan u = tan u0 + (tan uf − tan u0) t/t_f."""
    tan0, tan1 = np.tan(angles)
    g, a = GODDARD_G, GODDARD_A

    def rhs(t: float, s: np.ndarray) -> list[float]:
        tan_u = tan0 + (tan1 - tan0) * t / tf
        cos_u = 1.0 / np.sqrt(1.0 + tan_u * tan_u)
        return [s[1], a * cos_u, s[3], -g + a * tan_u * cos_u]

    sol = solve_ivp(rhs, (0.0, tf), np.zeros(4), method="DOP853", rtol=_SHOOTING_RTOL,
                    atol=1e-14)
    return sol.y[:, -1]


def _goddard_residual(angles: np.ndarray, tf: float) -> np.ndarray:
    s = _goddard_final_state(angles, tf)
    return np.array([s[2] / GODDARD_H - 1.0, s[3] / (GODDARD_A * tf)])


def goddard_max_vx(tf: float, guess: tuple[float, float] = (0.6, 0.1)) -> tuple[float, np.ndarray]:
    """Maximum v_x(t_f) of the ascent at fixed t_f > :func:`goddard_min_time`.

    Solves for the linear tangent law's end angles (u0, uf) (rad), u(t) = arctan(tan u0 +
    (tan uf − tan u0) t/t_f), such that y(t_f) = h and v_y(t_f) = 0, from ``guess``. u is
    monotone, so u0 and uf bound it; both must lie in (−π/2, π/2). Returns (v_x(t_f), (u0, uf)).
    """
    sol = root(_goddard_residual, np.asarray(guess, dtype=float), args=(tf,), method="hybr",
               options={"xtol": 1e-13})
    angles = sol.x
    residual = np.max(np.abs(_goddard_residual(angles, tf)))
    if residual > _RESIDUAL_TOL:
        raise RuntimeError(f"Goddard shooting failed at t_f = {tf}: residual {residual:.2e}")
    if np.any(np.abs(angles) >= np.pi / 2):
        raise RuntimeError(f"Goddard control leaves [−π/2, π/2] at t_f = {tf}: {angles}")
    return float(_goddard_final_state(angles, tf)[1]), angles


def goddard_tf_grid(n_points: int) -> np.ndarray:
    """Final times of the Goddard front, shape (n_points,): t_f = t_min + (250 − t_min) s² for
    s uniform in [0, 1], denser near t_min where v_x*(t_f) rises like √(t_f − t_min)."""
    t_min = goddard_min_time()
    return t_min + (GODDARD_TF_MAX - t_min) * np.linspace(0.0, 1.0, n_points) ** 2


def goddard_reference_front(n_points: int = 400) -> np.ndarray:
    """Goddard Pareto front, shape (n_points, 2), rows (J1, J2) = (t_f, −v_x*(t_f)) sorted by
    t_f from :func:`goddard_min_time` (where J2 = 0) to 250.

    Continued from t_f = 250 downwards, each shooting problem started from the linear
    extrapolation of the two previous solutions.
    """
    if n_points < 2:
        raise ValueError(f"need at least 2 points, got {n_points}")
    tfs = goddard_tf_grid(n_points)
    j2 = np.zeros(n_points)  # J2(t_min) = 0: the bang-bang minimum-time solution
    history: list[tuple[float, np.ndarray]] = []
    guess = np.array([0.6, 0.1])
    for i in range(n_points - 1, 0, -1):
        tf = tfs[i]
        if len(history) >= 2:
            (t1, a1), (t2, a2) = history[-1], history[-2]
            guess = a1 + (a1 - a2) * (tf - t1) / (t1 - t2)
            guess = np.clip(guess, -np.pi / 2 + 1e-9, np.pi / 2 - 1e-9)
        vx, angles = goddard_max_vx(tf, tuple(guess))
        j2[i] = -vx
        history.append((tf, angles))
        guess = angles
    return np.column_stack([tfs, j2])


# --- maximum-energy orbit raising ------------------------------------------------------------

def _orbit_rhs(x: ca.SX, u: ca.SX) -> ca.SX:
    r, vr, vt = x[0], x[1], x[3]
    return ca.vertcat(vr, vt**2 / r - 1 / r**2 + ORBIT_A * ca.cos(u), vt / r,
                      -vt * vr / r + ORBIT_A * ca.sin(u))


def _energy(x: ca.SX | np.ndarray) -> ca.SX | float:
    return (x[1] ** 2 + x[3] ** 2) / 2 - 1 / x[0]


@lru_cache(maxsize=4)
def _orbit_nlp(intervals: int) -> tuple[ca.Function, np.ndarray, np.ndarray]:
    """Hermite–Simpson NLP (separated form) with K = ``intervals`` in normalised time τ = t/t_f.

    w = (u_0, then per interval k: x_{k+½}, x_{k+1}, u_{k+½}, u_{k+1}), parameter p = t_f,
    objective −E(x_K). Returns (solver, lbw, ubw).
    """
    k = intervals
    x, u, tf = ca.SX.sym("x", 4), ca.SX.sym("u"), ca.SX.sym("tf")
    f = ca.Function("f", [x, u, tf], [tf * _orbit_rhs(x, u)]).map(k)
    u0, w_mat = ca.SX.sym("u0"), ca.SX.sym("w", 10, k)
    xm, x1, um, u1 = w_mat[0:4, :], w_mat[4:8, :], w_mat[8, :], w_mat[9, :]
    xk = ca.horzcat(ca.DM(ORBIT_X0), x1[:, :-1])
    uk = ca.horzcat(u0, u1[:, :-1])
    fk, fm, f1 = f(xk, uk, tf), f(xm, um, tf), f(x1, u1, tf)
    h = 1.0 / k
    defects = ca.vertcat(xm - (xk + x1) / 2 - h / 8 * (fk - f1),
                         x1 - xk - h / 6 * (fk + 4 * fm + f1))
    w = ca.vertcat(u0, ca.vec(w_mat))
    nlp = {"x": w, "p": tf, "f": -_energy(x1[:, -1]), "g": ca.vec(defects)}
    solver = ca.nlpsol("orbit_hs", "ipopt", nlp, ipopt_options(1e-12, 3000))
    lbw, ubw = np.full(w.shape[0], -np.inf), np.full(w.shape[0], np.inf)
    block = 1 + np.arange(10 * k).reshape(k, 10)
    controls = np.concatenate([[0], block[:, 8:].ravel()])
    lbw[controls], ubw[controls] = -np.pi, np.pi
    lbw[block[:, [0, 4]].ravel()] = 0.1  # r stays away from the singularity
    return solver, lbw, ubw


def _samples_to_w(z: np.ndarray) -> np.ndarray:
    """(2K+1, 5) samples (x, u) at τ = j/(2K) → HS decision vector."""
    blocks = np.hstack([z[1::2, :4], z[2::2, :4], z[1::2, 4:], z[2::2, 4:]])
    return np.concatenate([[z[0, 4]], blocks.ravel()])


def _w_to_samples(w: np.ndarray) -> np.ndarray:
    """HS decision vector → (2K+1, 5) samples (x, u) at τ = j/(2K)."""
    blocks = w[1:].reshape(-1, 10)
    z = np.empty((2 * blocks.shape[0] + 1, 5))
    z[0, :4], z[0, 4] = ORBIT_X0, w[0]
    z[1::2, :4], z[2::2, :4] = blocks[:, 0:4], blocks[:, 4:8]
    z[1::2, 4], z[2::2, 4] = blocks[:, 8], blocks[:, 9]
    return z


def _velocity_aligned_samples(tf: float, intervals: int) -> np.ndarray:
    """Guess: thrust along the velocity (greatest dE/dt), samples (2K+1, 5) at τ = j/(2K)."""
    def rhs(t: float, s: np.ndarray) -> list[float]:
        r, vr, _, vt = s
        v = np.hypot(vr, vt)
        return [vr, vt**2 / r - 1 / r**2 + ORBIT_A * vr / v, vt / r,
                -vt * vr / r + ORBIT_A * vt / v]

    tau = np.linspace(0.0, 1.0, 2 * intervals + 1)
    sol = solve_ivp(rhs, (0.0, tf), ORBIT_X0, t_eval=tau * tf, rtol=1e-10, atol=1e-12)
    return np.column_stack([sol.y.T, np.arctan2(sol.y[3], sol.y[1])])


def _resample(z: np.ndarray, intervals: int) -> np.ndarray:
    """Samples at τ = j/(2K') linearly interpolated to K = ``intervals``."""
    old = np.linspace(0.0, 1.0, z.shape[0])
    new = np.linspace(0.0, 1.0, 2 * intervals + 1)
    return np.column_stack([np.interp(new, old, z[:, i]) for i in range(z.shape[1])])


def orbit_raising_max_energy(
    tf: float, intervals: int, guess: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """Maximum final specific energy E(t_f) of the orbit raising at fixed t_f.

    Hermite–Simpson transcription with K = ``intervals`` (IPOPT, tol 1e-12). ``guess`` is a
    (2K'+1, 5) array of samples (r, v_r, θ, v_t, u) at τ = j/(2K') for any K' (default: thrust
    along the velocity). Returns (E, samples of shape (2K+1, 5)).
    """
    solver, lbw, ubw = _orbit_nlp(intervals)
    z = _velocity_aligned_samples(tf, intervals) if guess is None else _resample(guess, intervals)
    sol = solver(x0=_samples_to_w(z), p=tf, lbx=lbw, ubx=ubw, lbg=0, ubg=0)
    status = solver.stats()["return_status"]
    if not solver.stats()["success"]:
        raise RuntimeError(f"orbit raising NLP failed at t_f = {tf}, K = {intervals}: {status}")
    return -float(sol["f"]), _w_to_samples(np.asarray(sol["x"]).ravel())


def orbit_raising_mesh_refinement(
    tfs: tuple[float, ...] = ORBIT_TEST_TF, start: int = 25, rtol: float = 1e-8,
    max_intervals: int = 6400,
) -> tuple[int, list[tuple[int, list[float]]]]:
    """Double K from ``start`` until the maximum energy at every t_f in ``tfs`` changes by less
    than ``rtol`` relative. Returns (K, table of (K, [E(t_f) for t_f in tfs]))."""
    table: list[tuple[int, list[float]]] = []
    guesses: list[np.ndarray | None] = [None] * len(tfs)
    k = start
    while k <= max_intervals:
        energies = []
        for i, tf in enumerate(tfs):
            energy, guesses[i] = orbit_raising_max_energy(tf, k, guesses[i])
            energies.append(energy)
        table.append((k, energies))
        if len(table) > 1:
            previous = np.array(table[-2][1])
            if np.all(np.abs(np.array(energies) - previous) < rtol * np.abs(energies)):
                return k, table
        k *= 2
    raise RuntimeError(f"orbit raising mesh not converged to {rtol} with K ≤ {max_intervals}")


def orbit_raising_reference_front(
    n_points: int = 200, intervals: int | None = None
) -> np.ndarray:
    """Orbit-raising Pareto front, shape (n_points, 2), rows (J1, J2) = (t_f, −E*(t_f)) for t_f
    uniform in [20, 80].

    K = ``intervals`` (default: from :func:`orbit_raising_mesh_refinement`), each t_f started
    from the previous t_f's solution.
    """
    if n_points < 2:
        raise ValueError(f"need at least 2 points, got {n_points}")
    if intervals is None:
        intervals, _ = orbit_raising_mesh_refinement()
    tfs = np.linspace(*ORBIT_TF, n_points)
    j2 = np.empty(n_points)
    guess = None
    for i, tf in enumerate(tfs):
        energy, guess = orbit_raising_max_energy(tf, intervals, guess)
        j2[i] = -energy
    return np.column_stack([tfs, j2])


# --- packaged fronts -------------------------------------------------------------------------

def reference_front(problem: str) -> np.ndarray:
    """The packaged reference front of ``problem`` ("goddard" or "orbit-raising"), shape (n, 2),
    rows (J1, J2) sorted by J1."""
    if problem not in FILES:
        raise ValueError(f"unknown problem {problem!r}; choose one of {sorted(FILES)}")
    path = resources.files("ocpar.macs").joinpath("data", FILES[problem])
    with path.open() as stream:
        return np.loadtxt(stream, delimiter=",", skiprows=1, ndmin=2)


def write_front(path: Path, front: np.ndarray) -> None:
    """Write a front as CSV with header ``J1,J2`` and full float precision."""
    np.savetxt(path, front, fmt="%.17g", delimiter=",", header="J1,J2", comments="")
