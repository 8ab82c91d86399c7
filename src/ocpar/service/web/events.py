"""Progress lines of a run → figures, for the event stream (``GET /jobs/{id}/events``).

The schemes print one line per superstep (formation, pursuit) or iteration (MACS) of
``NAME VALUE [UNIT]`` pairs::

    superstep    3  cost 1.470244198995e+07  equidistance 7.4e-16 rad  wall     1.5 ms
    superstep    5  agents in flight   3  finished     1  last final mass 512.795059 kg  ...
    iteration    2  evaluations    218  archive  10  hypervolume 0.763327

:func:`parse_progress` reads such a line into its superstep (None on lines without one) and
its figures: each number under the words before it (``"agents in flight": 3.0``), units
(a short word right after a number) dropped.
"""

from __future__ import annotations

import math
import re

#: A number as the schemes print them (integers, decimals, exponents, inf, nan).
NUMBER = re.compile(r"[-+]?(?:\d+\.?\d*(?:[eE][-+]?\d+)?|\.\d+(?:[eE][-+]?\d+)?|inf|nan)\Z")
#: The counter a progress line starts with.
COUNTER = re.compile(r"\s*(superstep|iteration)\s+(\d+)\b")
#: Units the schemes print after a figure.
UNITS = frozenset({"rad", "ms", "s", "kg", "m", "km", "deg", "%"})


def parse_progress(line: str) -> tuple[int | None, dict[str, float]]:
    """The superstep and the figures of a progress line (``(None, {})`` for any other line;
    ``iteration K`` lines give the figure ``iteration``, not a superstep)."""
    match = COUNTER.match(line)
    if not match:
        return None, {}
    counter, value = match.group(1), int(match.group(2))
    figures: dict[str, float] = {} if counter == "superstep" else {"iteration": float(value)}
    words: list[str] = []
    after_number = False
    for token in line[match.end():].split():
        if NUMBER.match(token):
            number = float(token)
            if words and math.isfinite(number):
                figures[" ".join(words)] = number
            words, after_number = [], True
            continue
        if not (after_number and token in UNITS):
            words.append(token)
        after_number = False
    return (value if counter == "superstep" else None), figures
