"""The Sun–Earth/Moon CRTBP and the L2 halo orbit from differential correction."""

from __future__ import annotations

import numpy as np
import pytest

from ocpar.models.crtbp import (
    LENGTH_UNIT_KM,
    SUN_EARTH_MU,
    TIME_UNIT_DAYS,
    Crtbp,
    HaloOrbit,
    _integrate,
    halo_orbit,
    richardson_guess,
)

MODEL = Crtbp()


@pytest.fixture(scope="module")
def halo() -> HaloOrbit:
    return halo_orbit()


def test_l2_point():
    mu = SUN_EARTH_MU
    x_l2 = MODEL.l2_point()
    assert abs(MODEL.potential_gradient([x_l2, 0.0, 0.0])[0]) <= 1e-14
    assert (x_l2 - (1 - mu)) / (mu / 3) ** (1 / 3) == pytest.approx(1.0, rel=0.05)
    assert 1.0095 < x_l2 < 1.0105


@pytest.mark.parametrize("position", [[1.0101, 0.002, 0.0015], [1.0, -0.01, 0.02],
                                      [0.3, 0.4, -0.2]])
def test_potential_derivatives_match_finite_differences(position):
    x = np.array(position)
    step = 1e-6
    grad_fd = np.array([(MODEL.potential(x + step * e) - MODEL.potential(x - step * e))
                        / (2 * step) for e in np.eye(3)])
    grad = MODEL.potential_gradient(x)
    assert np.allclose(grad, grad_fd, rtol=1e-6, atol=1e-6 * np.abs(grad).max())
    hess_fd = np.array([(MODEL.potential_gradient(x + step * e)
                         - MODEL.potential_gradient(x - step * e)) / (2 * step)
                        for e in np.eye(3)])
    hess = MODEL.potential_hessian(x)
    assert np.allclose(hess, hess.T)
    assert np.abs(hess - hess_fd).max() <= 1e-6 * np.abs(hess).max()


def test_state_transition_matrix_matches_finite_differences(halo):
    """The variational equations (Hessian and Coriolis blocks) against perturbed flows."""
    t = 0.8
    s0 = halo.initial_state
    y0 = np.concatenate([s0, np.eye(6).ravel()])
    phi = _integrate(MODEL.variational_rhs, t, y0).y[6:, -1].reshape(6, 6)
    step = 1e-7
    phi_fd = np.column_stack([
        (_integrate(MODEL.rhs, t, s0 + step * e).y[:, -1]
         - _integrate(MODEL.rhs, t, s0 - step * e).y[:, -1]) / (2 * step)
        for e in np.eye(6)])
    assert np.abs(phi - phi_fd).max() <= 1e-6 * np.abs(phi).max()


def test_halo_initial_state_and_amplitude(halo):
    """Northern family: the initial state is the maximum of z, beyond L2; half a period later
    the orbit crosses y = 0 at its minimum z < 0, nearer the EMB, with ẋ = ż = 0 there too."""
    s0 = halo.initial_state
    assert s0[1] == s0[3] == s0[5] == 0.0
    assert s0[2] > 0 and s0[0] > MODEL.l2_point()
    z_max = halo.vertical_amplitude_km
    assert z_max == pytest.approx(s0[2] * LENGTH_UNIT_KM, rel=1e-12)
    assert 200_000 < z_max < 230_000  # ≈ 227,900
    half = halo.state(halo.period / 2)
    assert np.abs(half[[1, 3, 5]]).max() <= 1e-10
    assert half[0] < MODEL.l2_point() and half[2] < 0
    z_min = half[2] * LENGTH_UNIT_KM
    assert -182_000 < z_min < -177_000  # ≈ −179,600
    # Richardson's Az is, to third order, half the peak-to-peak vertical extent
    assert (z_max - z_min) / 2 == pytest.approx(205_000, rel=0.015)


def test_halo_period_and_periodicity(halo):
    assert halo.periodicity_error() <= 1e-10
    assert 179.9 < halo.period * TIME_UNIT_DAYS < 180.5
    times = np.array([0.3, 0.3 + halo.period, 0.3 - 2 * halo.period])
    states = halo.states(times)
    assert np.abs(states - states[0]).max() <= 1e-12


def test_richardson_guess_is_close_to_the_corrected_orbit(halo):
    guess, period = richardson_guess(205_000.0, MODEL)
    assert guess[2] == halo.initial_state[2]  # z0 is held fixed by the correction
    assert abs(guess[0] - halo.initial_state[0]) * LENGTH_UNIT_KM < 10_000
    assert guess[4] == pytest.approx(halo.initial_state[4], rel=0.01)
    assert period == pytest.approx(halo.period, rel=0.005)


def test_states_match_single_integrations(halo):
    times = np.array([2.9, 0.0, 1.1, 4.7, 1.1])
    states = halo.states(times)
    assert states.shape == (5, 6)
    for t, s in zip(times, states, strict=True):
        assert np.abs(halo.state(t) - s).max() <= 1e-12
    assert np.array_equal(states[1], halo.initial_state)
    hessians = halo.potential_hessians(times)
    assert hessians.shape == (5, 3, 3)
    assert np.array_equal(hessians[2], MODEL.potential_hessian(states[2, :3]))


def test_monodromy_eigenvalue_structure(halo):
    monodromy = halo.monodromy()
    assert np.linalg.det(monodromy) == pytest.approx(1.0, abs=1e-8)
    eig = np.linalg.eigvals(monodromy)
    # the trivial pair is a Jordan block at 1: its eigenvalues split like sqrt(error × |M|)
    trivial = np.abs(eig - 1) <= 1e-5
    assert trivial.sum() == 2
    rest = eig[~trivial]
    real = np.sort(rest[np.abs(rest.imag) <= 1e-9].real)
    assert real.size == 2
    assert 1_000 < real[1] < 2_500  # the unstable manifold of a Sun–Earth L2 halo
    assert real[0] * real[1] == pytest.approx(1.0, abs=1e-6)
    center = rest[np.abs(rest.imag) > 1e-9]
    assert center.size == 2 and center[0] == pytest.approx(np.conj(center[1]))
    assert np.abs(np.abs(center) - 1).max() <= 1e-6


def test_jacobi_constant_is_conserved(halo):
    states = halo.states(np.linspace(0.0, halo.period, 60))
    jacobi = np.array([MODEL.jacobi_constant(s) for s in states])
    assert np.ptp(jacobi) <= 1e-11
    assert 3.0 < jacobi[0] < 3.001


@pytest.mark.parametrize("az_km", [-5.0, 10_000.0, 1e6, np.nan])
def test_bad_amplitude_raises(az_km):
    with pytest.raises(ValueError, match="az_km"):
        halo_orbit(az_km)


@pytest.mark.parametrize("mu", [0.7, 0.0, 0.5, np.inf])
def test_bad_mass_parameter_raises(mu):
    with pytest.raises(ValueError, match="mu"):
        Crtbp(mu)


def test_bad_halo_fields_raise():
    with pytest.raises(ValueError, match="initial_state"):
        HaloOrbit(MODEL, np.zeros(5), 3.0)
    with pytest.raises(ValueError, match="period"):
        HaloOrbit(MODEL, np.ones(6), -1.0)
    with pytest.raises(ValueError, match="tol"):
        halo_orbit(tol=0.0)
