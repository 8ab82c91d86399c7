"""Couplings of the final formation: the potential, equal arc length, user couplings, and the
potential's critical sets off a circle."""
