"""Example run configurations for the papers' examples: ``ocpar run --list``, ``ocpar run
NAME`` (see :mod:`ocpar.config`)."""
