"""The schemes by name: each one's options dataclass (:class:`ocpar.driver.SchemeRun`), named
by module and class and imported on first use (this module imports no other of ocpar's)."""

from __future__ import annotations

import importlib

#: The schemes a configuration can run, and the module of each one's options dataclass.
SCHEMES = {
    "formation": ("ocpar.formation.run", "FormationRun"),
    "pursuit": ("ocpar.pursuit.run", "PursuitRun"),
    "macs": ("ocpar.macs.run", "MacsRun"),
}


def scheme_class(scheme: str) -> type:
    """The options dataclass of ``scheme`` (its fields are the configuration's keys)."""
    module, name = SCHEMES[scheme]
    return getattr(importlib.import_module(module), name)
