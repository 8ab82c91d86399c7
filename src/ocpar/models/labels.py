"""Names and units of a model's components, as its results label them.

A model (an :class:`~ocpar.models.OdeModel`, a :class:`~ocpar.models.MechanicalSystem`) may
name its state and control entries and give their units, as optional members:

* ``state_names``, ``control_names``: one string per entry (a mechanical system's state is its
  configuration q);
* ``state_units``, ``control_units``: one unit string for all entries, or one per entry;
* ``time_unit``: the unit of t (of T, h, the sample times);
* ``cost_unit``: the unit of the running cost's integral (the inner optimal cost);
* ``name``: the model's name in the results (default: its class's name, :func:`model_name`).

Units are strings a unit library parses (pint: ``m``, ``s``, ``kg``, ``N``,
``m/s``, ``Mm/min``); ``1`` (the default) is a nondimensional quantity, as in the papers'
examples. Without names the entries are ``x0``, ``x1``, ... and ``u0``, ``u1``, ...
(:func:`state_labels`, :func:`control_labels`). The result files read them here and nowhere
else (:mod:`ocpar.results`).
"""

from __future__ import annotations

from dataclasses import dataclass

DIMENSIONLESS = "1"


@dataclass(frozen=True)
class Labels:
    """The entries of a vector quantity: ``names`` (n,) and ``units`` (n,) unit strings."""

    names: tuple[str, ...]
    units: tuple[str, ...]

    @property
    def unit(self) -> str | None:
        """The common unit of every entry (None if they differ; '1' for no entries)."""
        distinct = set(self.units)
        return distinct.pop() if len(distinct) == 1 else None if distinct else DIMENSIONLESS

    def per(self, time: str, order: int = 1) -> Labels:
        """The labels of these entries' ``order``-th time derivative (velocity: 1,
        acceleration: 2), each entry's unit divided by ``time`` to that power
        (:func:`derived`): (m, m, rad) per s is (m/s, m/s, rad/s)."""
        return Labels(self.names, tuple(derived((u, 1), (time, -order)) for u in self.units))


def _labels(model: object, kind: str, n: int, default: tuple[str, ...]) -> Labels:
    """``model``'s ``<kind>_names`` and ``<kind>_units`` for its ``n`` entries, defaulting to
    ``default`` and '1'; one ValueError naming the member for a bad one."""
    name = type(model).__name__
    names = getattr(model, f"{kind}_names", None)
    names = default if names is None else tuple(names)
    if len(names) != n or not all(isinstance(s, str) and s for s in names):
        raise ValueError(f"{name}.{kind}_names: need {n} non-empty strings, got {names!r}")
    if len(set(names)) != n:
        raise ValueError(f"{name}.{kind}_names: names repeat: {names!r}")
    units = getattr(model, f"{kind}_units", None)
    units = (DIMENSIONLESS,) * n if units is None else (
        (units,) * n if isinstance(units, str) else tuple(units))
    if len(units) != n or not all(isinstance(u, str) and u.strip() for u in units):
        raise ValueError(f"{name}.{kind}_units: need one unit string or {n}, got {units!r}")
    return Labels(names, units)


def state_labels(model: object, n: int, default: tuple[str, ...] | None = None) -> Labels:
    """The names and units of ``model``'s ``n`` state entries (``state_names``,
    ``state_units``; defaults ``default`` or ``x<i>``, and '1')."""
    return _labels(model, "state", n, default or tuple(f"x{i}" for i in range(n)))


def control_labels(model: object, n: int) -> Labels:
    """The names and units of ``model``'s ``n`` control entries (``control_names``,
    ``control_units``; defaults ``u<i>`` and '1')."""
    return _labels(model, "control", n, tuple(f"u{i}" for i in range(n)))


def _unit(model: object, member: str) -> str:
    unit = getattr(model, member, DIMENSIONLESS)
    if not isinstance(unit, str) or not unit.strip():
        raise ValueError(f"{type(model).__name__}.{member}: need a unit string, got {unit!r}")
    return unit


def time_unit(model: object) -> str:
    """The unit of ``model``'s time (``time_unit``; default '1')."""
    return _unit(model, "time_unit")


def cost_unit(model: object) -> str:
    """The unit of ``model``'s integrated running cost (``cost_unit``; default '1')."""
    return _unit(model, "cost_unit")


def mass_unit(model: object) -> str:
    """The unit of ``model``'s ``mass`` (``mass_unit``; default '1')."""
    return _unit(model, "mass_unit")


def model_name(model: object) -> str:
    """``model``'s name in the results: its ``name`` member where that is a non-empty string
    (a model from expressions, :func:`~ocpar.models.ode_model`), else its class's name."""
    name = getattr(model, "name", None)
    return name if isinstance(name, str) and name else type(model).__name__


def check_labels(model: object, nx: int, nu: int, field: str = "model") -> None:
    """Raise one ValueError (prefixed by ``field``) unless ``model``'s optional names and
    units (module docstring) fit its ``nx`` state and ``nu`` control entries."""
    try:
        state_labels(model, nx)
        control_labels(model, nu)
        for member in ("time_unit", "cost_unit", "mass_unit"):
            _unit(model, member)
    except ValueError as exc:
        raise ValueError(f"{field}: {exc}") from None


def derived(*factors: tuple[str, int]) -> str:
    """The unit of a product of powers of units, each factor (unit, exponent): e.g.
    ``derived(("m", 1), ("s", -1))`` is 'm/s', ``derived(("kg", 1), ("m", 1), ("s", -2))``
    'kg*m/s**2', ``derived(("N", 2), ("s", 1))`` 'N**2*s'. The one place a derived
    quantity's unit (a velocity's, a force's, a cost's) is formed: '1' factors and zero
    exponents are left out, a compound unit is parenthesised, '1' if nothing is left."""
    def power(unit: str, exponent: int) -> str:
        base = unit if unit.replace("_", "").isalnum() else f"({unit})"
        return base if exponent == 1 else f"{base}**{exponent}"

    kept = [(u.strip(), e) for u, e in factors if e != 0 and u.strip() != DIMENSIONLESS]
    above = "*".join(power(u, e) for u, e in kept if e > 0)
    below = [power(u, -e) for u, e in kept if e < 0]
    if not below:
        return above or DIMENSIONLESS
    over = below[0] if len(below) == 1 else f"({'*'.join(below)})"
    return f"{above or DIMENSIONLESS}/{over}"
