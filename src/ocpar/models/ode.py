"""What a controlled ODE model must provide to the multiple-shooting transcription, and the
checks of a model a user brings."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import casadi as ca
import numpy as np

from ocpar.models.labels import check_labels


@runtime_checkable
class OdeModel(Protocol):
    """A controlled ODE ẋ = f(x, u) with a running cost g(x, u) ≥ 0.

    Implementations are frozen dataclasses (hashable cache keys, picklable by reference, no
    CasADi objects). ``rhs`` and ``running_cost`` are written with CasADi operations on
    ``casadi.SX`` arguments. A model may also define ``control_bounds()`` (same form as
    ``state_bounds``); without it the controls are unbounded (see :func:`control_bounds`).
    As a formation's agent (:class:`~ocpar.ocp.MsEndpointShape`) it names its
    ``position_indices`` (the state entries placed on the target) and may define
    ``guess(starts, ends, times)``: states (k, N+1, nx) and controls (k, N, nu) from the
    start and end states (k, nx) at the node times (N+1,), the inner solves' first guess
    (without it: the straight line, zero controls).
    """

    @property
    def nx(self) -> int:
        """Dimension of the state x."""
        ...

    @property
    def nu(self) -> int:
        """Dimension of the control u."""
        ...

    def rhs(self, x: ca.SX, u: ca.SX) -> ca.SX:
        """f(x, u), shape (nx, 1)."""
        ...

    def running_cost(self, x: ca.SX, u: ca.SX) -> ca.SX:
        """g(x, u), scalar."""
        ...

    def state_bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper bounds (nx,) on every state sample (±inf where unbounded)."""
        ...


def control_bounds(model: OdeModel) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds (nu,) on every control: the model's ``control_bounds()`` if it
    defines one, else ±inf."""
    bounds = getattr(model, "control_bounds", None)
    if bounds is None:
        return np.full(model.nu, -np.inf), np.full(model.nu, np.inf)
    lower, upper = bounds()
    return np.asarray(lower, float), np.asarray(upper, float)


def ode_functions(model: OdeModel) -> tuple[ca.Function, ca.Function]:
    """f(x, u) and g(x, u) of ``model`` as CasADi Functions (for numerical evaluation and
    integration outside an NLP)."""
    x, u = ca.SX.sym("x", model.nx), ca.SX.sym("u", model.nu)
    return (ca.Function("f", [x, u], [model.rhs(x, u)]),
            ca.Function("g", [x, u], [model.running_cost(x, u)]))


def check_ode_model(model: object, field: str = "model") -> None:
    """Raise one ValueError naming ``field`` unless ``model`` is an :class:`OdeModel` whose
    dimensions are positive integers, whose ``rhs`` and ``running_cost`` build CasADi
    expressions of shapes (nx, 1) and (1, 1), and whose bounds have the right shapes with
    lower ≤ upper (NaN nowhere), and whose names and units fit
    (:func:`~ocpar.models.labels.check_labels`)."""
    missing = [name for name in ("nx", "nu", "rhs", "running_cost", "state_bounds")
               if not hasattr(model, name)]
    if missing:
        raise ValueError(f"{field}: not an OdeModel, it lacks {', '.join(missing)}")
    nx, nu = model.nx, model.nu  # type: ignore[attr-defined]
    for name, n in (("nx", nx), ("nu", nu)):
        if not isinstance(n, int | np.integer) or isinstance(n, bool) or n < 1:
            raise ValueError(f"{field}.{name}: must be a positive integer, got {n!r}")
    x, u = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
    for name, shape in (("rhs", (nx, 1)), ("running_cost", (1, 1))):
        try:
            expr = ca.SX(getattr(model, name)(x, u))
        except Exception as exc:
            raise ValueError(f"{field}.{name}: does not evaluate on CasADi symbols "
                             f"x ({nx},), u ({nu},): {type(exc).__name__}: {exc}".splitlines()[0]
                             ) from None
        if expr.shape != shape:
            raise ValueError(f"{field}.{name}: shape {expr.shape}, expected {shape}")
    bounds = {"state_bounds": (nx, lambda: model.state_bounds())}  # type: ignore[attr-defined]
    if hasattr(model, "control_bounds"):
        bounds["control_bounds"] = (nu, lambda: model.control_bounds())  # type: ignore[attr-defined]
    for name, (n, get) in bounds.items():
        try:
            lower, upper = (np.asarray(b, float) for b in get())
        except Exception as exc:
            raise ValueError(f"{field}.{name}: must return (lower, upper) arrays of shape "
                             f"({n},): {type(exc).__name__}: {exc}".splitlines()[0]) from None
        if lower.shape != (n,) or upper.shape != (n,):
            raise ValueError(f"{field}.{name}: shapes {lower.shape} and {upper.shape}, "
                             f"expected ({n},)")
        if np.isnan(lower).any() or np.isnan(upper).any() or (lower > upper).any():
            raise ValueError(f"{field}.{name}: need lower <= upper, no NaN")
    check_labels(model, nx, nu, field)
