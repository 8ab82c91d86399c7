"""IPOPT settings shared by the transcriptions."""

from __future__ import annotations


def ipopt_options(tol: float, max_iter: int, **extra: object) -> dict:
    """Silent IPOPT options with the given tolerance (exact Hessians, MUMPS); ``extra`` are
    further IPOPT options."""
    return {
        "print_time": False,
        "ipopt": {"print_level": 0, "sb": "yes", "tol": tol, "max_iter": max_iter, **extra},
    }
