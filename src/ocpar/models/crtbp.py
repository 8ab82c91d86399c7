"""Circular restricted three-body problem (CRTBP) and L2 halo orbits, Sun–Earth/Moon system.

Normalised rotating frame with angular rate 1: length unit 1 AU (``LENGTH_UNIT_KM``), time unit
1 year / 2π (``TIME_UNIT_DAYS``). The Sun (mass 1−μ) sits at (−μ, 0, 0) and the Earth–Moon
barycentre (EMB, mass μ) at (1−μ, 0, 0). This is the standard placement; the source paper's
eq. 1 swaps the two primaries. With the effective potential

    Ω(x) = ½(x1² + x2²) + (1−μ)/r1 + μ/r2,   r1 = |x − (−μ, 0, 0)|,  r2 = |x − (1−μ, 0, 0)|,

the equations of motion are ẍ1 − 2ẋ2 = ∂Ω/∂x1, ẍ2 + 2ẋ1 = ∂Ω/∂x2, ẍ3 = ∂Ω/∂x3, for the state
s = (x, ẋ) ∈ R⁶.

Halo orbits are of the northern family: their larger excursion from the ecliptic is towards
+z. The initial state is the crossing of the x–z plane beyond L2 (away from the EMB), where z is
at its maximum, z0 > 0; half a period later the orbit crosses the plane again on the EMB side at
its minimum z < 0, of smaller magnitude. The requested ``az_km`` is Richardson's amplitude, close
to half the peak-to-peak vertical extent; z0 is larger. The default, az_km = 205,000, gives
max z ≈ 227,900 km and half the extent ≈ 203,700 km: both in the 200,000–230,000 km of the
halos such missions use.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property

import numpy as np

SUN_EARTH_MU = 3.040357e-6
LENGTH_UNIT_KM = 149_597_870.7
TIME_UNIT_DAYS = 365.25 / (2 * np.pi)

RTOL = 3e-14  # close to DOP853's floor of 100 × machine epsilon
ATOL = 1e-15
MAX_CORRECTIONS = 30
AZ_RANGE_KM = (50_000.0, 600_000.0)

# velocity block of the variational matrix: ẍ = 2 (ẋ2, −ẋ1, 0) + ∇Ω
CORIOLIS = np.array([[0.0, 2.0, 0.0], [-2.0, 0.0, 0.0], [0.0, 0.0, 0.0]])


def _integrate(fun: Callable, t_end: float, y0: np.ndarray, t_start: float = 0.0, **kwargs):
    """solve_ivp with DOP853 at the module's tolerances, from t_start to t_end."""
    from scipy.integrate import solve_ivp
    return solve_ivp(fun, (t_start, t_end), y0, method="DOP853", rtol=RTOL, atol=ATOL, **kwargs)


@dataclass(frozen=True)
class Crtbp:
    """CRTBP with mass parameter ``mu`` = m2 / (m1 + m2) in (0, 0.5)."""

    mu: float = SUN_EARTH_MU

    def __post_init__(self) -> None:
        if not (np.isfinite(self.mu) and 0.0 < self.mu < 0.5):
            raise ValueError(f"Crtbp.mu must be a finite number in (0, 0.5), got {self.mu}")

    def _primaries(self) -> tuple[tuple[float, np.ndarray], ...]:
        """(mass, position) of the Sun and of the EMB."""
        mu = self.mu
        return ((1.0 - mu, np.array([-mu, 0.0, 0.0])), (mu, np.array([1.0 - mu, 0.0, 0.0])))

    def potential(self, x: np.ndarray) -> float:
        """Ω at position x (3,), normalised units."""
        x = np.asarray(x, dtype=float)
        gravity = sum(m / np.linalg.norm(x - p) for m, p in self._primaries())
        return 0.5 * (x[0] ** 2 + x[1] ** 2) + gravity

    def potential_gradient(self, x: np.ndarray) -> np.ndarray:
        """∇Ω at position x (3,); returns (3,)."""
        x = np.asarray(x, dtype=float)
        grad = np.array([x[0], x[1], 0.0])
        for m, p in self._primaries():
            d = x - p
            grad -= m * d / np.linalg.norm(d) ** 3
        return grad

    def potential_hessian(self, x: np.ndarray) -> np.ndarray:
        """Hessian of Ω at position x (3,), closed form; returns (3, 3)."""
        x = np.asarray(x, dtype=float)
        hess = np.diag([1.0, 1.0, 0.0])
        for m, p in self._primaries():
            d = x - p
            r = np.linalg.norm(d)
            hess += m * (3.0 * np.outer(d, d) / r**5 - np.eye(3) / r**3)
        return hess

    def rhs(self, t: float, s: np.ndarray) -> np.ndarray:
        """Time derivative of the state s = (x, ẋ) (6,); t is unused (autonomous)."""
        acc = self.potential_gradient(s[:3]) + CORIOLIS @ s[3:]
        return np.concatenate([s[3:], acc])

    def variational_rhs(self, t: float, y: np.ndarray) -> np.ndarray:
        """Derivative of y = (s, vec(Φ)) (42,), Φ the 6×6 state transition matrix (row-major),
        with Φ̇ = A Φ, A = [[0, I], [K, CORIOLIS]], K = potential_hessian."""
        s, phi = y[:6], y[6:].reshape(6, 6)
        a = np.zeros((6, 6))
        a[:3, 3:] = np.eye(3)
        a[3:, :3] = self.potential_hessian(s[:3])
        a[3:, 3:] = CORIOLIS
        return np.concatenate([self.rhs(t, s), (a @ phi).ravel()])

    def l2_point(self) -> float:
        """x-coordinate of L2 (beyond the EMB), root of ∂Ω/∂x1 on the x-axis."""
        from scipy.optimize import brentq
        hill = (self.mu / 3.0) ** (1.0 / 3.0)
        return brentq(lambda x: self.potential_gradient([x, 0.0, 0.0])[0],
                      1.0 - self.mu + 0.1 * hill, 2.0, xtol=1e-300, rtol=4 * np.finfo(float).eps)

    def jacobi_constant(self, s: np.ndarray) -> float:
        """Jacobi constant C = 2Ω(x) − |ẋ|² of the state s (6,)."""
        s = np.asarray(s, dtype=float)
        return 2.0 * self.potential(s[:3]) - float(s[3:] @ s[3:])


@dataclass(frozen=True, eq=False)
class HaloOrbit:
    """A periodic orbit of ``crtbp`` of ``period`` (normalised time) through ``initial_state``
    (6,), normalised units. ``halo_orbit`` puts the initial state on the x–z plane
    (y = ẋ = ż = 0) at the orbit's maximum z > 0 (northern family)."""

    crtbp: Crtbp
    initial_state: np.ndarray
    period: float

    def __post_init__(self) -> None:
        state = np.array(self.initial_state, dtype=float)
        if state.shape != (6,) or not np.all(np.isfinite(state)):
            raise ValueError(f"HaloOrbit.initial_state must be 6 finite numbers, got {state}")
        if not (np.isfinite(self.period) and self.period > 0):
            raise ValueError(f"HaloOrbit.period must be finite and > 0, got {self.period}")
        state.flags.writeable = False
        object.__setattr__(self, "initial_state", state)

    def state(self, t: float) -> np.ndarray:
        """State (6,) at time t (normalised), integrated from the initial state."""
        return self.states(np.array([t]))[0]

    def states(self, times: np.ndarray) -> np.ndarray:
        """States (len(times), 6) at the given times, each integrated from the initial state
        over t mod period (in increasing order, segment by segment, without interpolation)."""
        phases = np.mod(np.asarray(times, dtype=float).ravel(), self.period)
        order = np.argsort(phases)
        out = np.empty((phases.size, 6))
        t_prev, s_prev = 0.0, self.initial_state
        for i in order:
            if phases[i] > t_prev:
                sol = _integrate(self.crtbp.rhs, phases[i], s_prev, t_start=t_prev)
                t_prev, s_prev = phases[i], sol.y[:, -1]
            out[i] = s_prev
        return out

    @cached_property
    def _monodromy(self) -> np.ndarray:
        y0 = np.concatenate([self.initial_state, np.eye(6).ravel()])
        sol = _integrate(self.crtbp.variational_rhs, self.period, y0)
        return sol.y[6:, -1].reshape(6, 6)

    def monodromy(self) -> np.ndarray:
        """State transition matrix (6, 6) over one period."""
        return self._monodromy.copy()

    def periodicity_error(self) -> float:
        """max |s(period) − s(0)| (normalised units)."""
        end = _integrate(self.crtbp.rhs, self.period, self.initial_state).y[:, -1]
        return float(np.max(np.abs(end - self.initial_state)))

    def potential_hessians(self, times: np.ndarray) -> np.ndarray:
        """K(t) = Hessian of Ω at the halo position at each time; returns (len(times), 3, 3)."""
        hessians = [self.crtbp.potential_hessian(s[:3]) for s in self.states(times)]
        return np.array(hessians).reshape(-1, 3, 3)

    @cached_property
    def vertical_amplitude_km(self) -> float:
        """max |z| over the orbit (km), from the states where ż = 0."""
        def vertical_velocity(t, s):
            return s[5]

        sol = _integrate(self.crtbp.rhs, self.period, self.initial_state,
                         events=vertical_velocity)
        z = np.concatenate([[self.initial_state[2]], sol.y_events[0][:, 2]])
        return float(np.max(np.abs(z)) * LENGTH_UNIT_KM)


def richardson_guess(az_km: float, crtbp: Crtbp) -> tuple[np.ndarray, float]:
    """Richardson's (1980) third-order approximation of the northern L2 halo of amplitude
    ``az_km`` (km): the state (6,) at its maximum z, on the x–z plane, and the period."""
    mu = crtbp.mu
    gamma = crtbp.l2_point() - (1.0 - mu)

    def c(n: int) -> float:
        return (-1) ** n * (mu + (1 - mu) * gamma ** (n + 1) / (1 + gamma) ** (n + 1)) / gamma**3

    c2, c3, c4 = c(2), c(3), c(4)
    lam = np.sqrt(0.5 * (2 - c2 + np.sqrt((c2 - 2) ** 2 + 4 * (c2 - 1) * (1 + 2 * c2))))
    lam2 = lam**2
    k = 2 * lam / (lam2 + 1 - c2)
    delta = lam2 - c2

    d1 = 3 * lam2 / k * (k * (6 * lam2 - 1) - 2 * lam)
    d2 = 8 * lam2 / k * (k * (11 * lam2 - 1) - 2 * lam)
    a21 = 3 * c3 * (k**2 - 2) / (4 * (1 + 2 * c2))
    a22 = 3 * c3 / (4 * (1 + 2 * c2))
    a23 = -3 * c3 * lam / (4 * k * d1) * (3 * k**3 * lam - 6 * k * (k - lam) + 4)
    a24 = -3 * c3 * lam / (4 * k * d1) * (2 + 3 * k * lam)
    b21 = -3 * c3 * lam / (2 * d1) * (3 * k * lam - 4)
    b22 = 3 * c3 * lam / d1
    d21 = -c3 / (2 * lam2)
    a31 = (-9 * lam / (4 * d2) * (4 * c3 * (k * a23 - b21) + k * c4 * (4 + k**2))
           + (9 * lam2 + 1 - c2) / (2 * d2) * (3 * c3 * (2 * a23 - k * b21) + c4 * (2 + 3 * k**2)))
    a32 = -(9 * lam / 4 * (4 * c3 * (k * a24 - b22) + k * c4)
            + 1.5 * (9 * lam2 + 1 - c2) * (c3 * (k * b22 + d21 - 2 * a24) - c4)) / d2
    b31 = 3 / (8 * d2) * (8 * lam * (3 * c3 * (k * b21 - 2 * a23) - c4 * (2 + 3 * k**2))
                          + (9 * lam2 + 1 + 2 * c2) * (4 * c3 * (k * a23 - b21)
                                                        + k * c4 * (4 + k**2)))
    b32 = (9 * lam * (c3 * (k * b22 + d21 - 2 * a24) - c4)
           + 3 / 8 * (9 * lam2 + 1 + 2 * c2) * (4 * c3 * (k * a24 - b22) + k * c4)) / d2
    d31 = 3 / (64 * lam2) * (4 * c3 * a24 + c4)
    d32 = 3 / (64 * lam2) * (4 * c3 * (a23 - d21) + c4 * (4 + k**2))
    denom = 2 * lam * (lam * (1 + k**2) - 2 * k)
    s1 = (1.5 * c3 * (2 * a21 * (k**2 - 2) - a23 * (k**2 + 2) - 2 * k * b21)
          - 3 / 8 * c4 * (3 * k**4 - 8 * k**2 + 8)) / denom
    s2 = (1.5 * c3 * (2 * a22 * (k**2 - 2) + a24 * (k**2 + 2) + 2 * k * b22 + 5 * d21)
          + 3 / 8 * c4 * (12 - k**2)) / denom
    l1 = -1.5 * c3 * (2 * a21 + a23 + 5 * d21) - 3 / 8 * c4 * (12 - k**2) + 2 * lam2 * s1
    l2 = 1.5 * c3 * (a24 - 2 * a22) + 9 / 8 * c4 + 2 * lam2 * s2

    az = az_km / (LENGTH_UNIT_KM * gamma)  # in units of γ
    ax2 = -(l2 * az**2 + delta) / l1
    if not ax2 > 0:
        raise ValueError(f"no Richardson halo for az_km={az_km} and mu={mu}")
    ax = np.sqrt(ax2)
    rate = lam * (1 + s1 * ax**2 + s2 * az**2)  # dτ1/dt

    # Class II (δn = −1) at τ1 = π: the crossing of the x–z plane beyond L2, where z is largest.
    # Coordinates are centred on L2, scaled by γ, with the x-axis pointing away from the EMB.
    dn, cos1, cos2, cos3 = -1.0, -1.0, 1.0, -1.0
    x = (a21 * ax**2 + a22 * az**2 - ax * cos1 + (a23 * ax**2 - a24 * az**2) * cos2
         + (a31 * ax**3 - a32 * ax * az**2) * cos3)
    z = dn * (az * cos1 + d21 * ax * az * (cos2 - 3) + (d32 * az * ax**2 - d31 * az**3) * cos3)
    ydot = rate * (k * ax * cos1 + 2 * (b21 * ax**2 - b22 * az**2) * cos2
                   + 3 * (b31 * ax**3 - b32 * ax * az**2) * cos3)
    state = np.array([1 - mu + gamma * (1 + x), 0.0, gamma * z, 0.0, gamma * ydot, 0.0])
    return state, 2 * np.pi / rate


def halo_orbit(az_km: float = 205_000.0, crtbp: Crtbp = Crtbp(), tol: float = 1e-12) -> HaloOrbit:
    """Northern L2 halo of Richardson amplitude ``az_km`` (km): Richardson's third-order guess,
    then differential correction at fixed z0 (vary x0 and ẏ0) until ẋ and ż at the next crossing
    of y = 0 are at most ``tol`` (normalised velocity). Period = 2 × crossing time."""
    if not (np.isfinite(az_km) and AZ_RANGE_KM[0] < az_km < AZ_RANGE_KM[1]):
        raise ValueError(f"az_km must be in {AZ_RANGE_KM} km, got {az_km}")
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be finite and > 0, got {tol}")
    state, period = richardson_guess(az_km, crtbp)

    def crossing(t, y):
        return y[1]

    crossing.terminal = True
    crossing.direction = -np.sign(state[4])
    for _ in range(MAX_CORRECTIONS):
        y0 = np.concatenate([state, np.eye(6).ravel()])
        sol = _integrate(crtbp.variational_rhs, 2 * period, y0, events=crossing)
        if not sol.t_events[0].size:
            raise ValueError(f"halo correction for az_km={az_km}: no crossing of y = 0 found")
        half, y_half = sol.t_events[0][0], sol.y_events[0][0]
        s_half, phi = y_half[:6], y_half[6:].reshape(6, 6)
        residual = s_half[[3, 5]]
        period = 2 * half
        if np.max(np.abs(residual)) <= tol:
            return HaloOrbit(crtbp, state, period)
        # Newton step on (x0, ẏ0), the crossing time adjusting so that y stays 0
        acc = crtbp.rhs(half, s_half)
        jac = phi[np.ix_([3, 5], [0, 4])] - np.outer(acc[[3, 5]], phi[1, [0, 4]]) / s_half[4]
        state[[0, 4]] -= np.linalg.solve(jac, residual)
    raise ValueError(f"halo correction for az_km={az_km} did not converge in "
                     f"{MAX_CORRECTIONS} iterations")
