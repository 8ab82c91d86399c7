"""Matplotlib for writing PNG files from any process (no display): figures on the Agg canvas.

The schemes draw on :func:`figure`, a :class:`matplotlib.figure.Figure` with its own Agg
canvas: no ``pyplot`` (whose import, ~0.3–0.5 s, a run's picture need not pay) and no global
figure registry to close. Scripts may use :func:`pyplot`.
"""

from __future__ import annotations

import sys
import textwrap
from pathlib import Path
from types import ModuleType
from typing import Any


def figure(**kwargs: Any) -> Any:
    """A :class:`matplotlib.figure.Figure` (``kwargs``: its options, e.g. ``figsize``) on an
    Agg canvas of its own; draw with ``fig.subplots`` / ``fig.add_subplot``, write with
    :func:`save`."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(**kwargs)
    FigureCanvasAgg(fig)
    return fig


def subplots(*grid: int, figsize: tuple[float, float] | None = None, **kwargs: Any
             ) -> tuple[Any, Any]:
    """``pyplot.subplots`` on a :func:`figure`: the figure and its axes (``grid``: rows,
    columns; ``kwargs``: ``Figure.subplots``'s, e.g. ``sharex``, ``squeeze``)."""
    fig = figure(figsize=figsize)
    return fig, fig.subplots(*grid, **kwargs)


def pyplot() -> ModuleType:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (imported on first use)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig: Any, path: Path) -> Path:
    """Lay out ``fig``, write it to ``path`` as a 120-dpi PNG and close it (where pyplot
    holds it)."""
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    if (plt := sys.modules.get("matplotlib.pyplot")) is not None:
        plt.close(fig)
    return Path(path)


def wrapped(title: str, width: int = 70) -> str:
    """``title`` broken into lines of at most ``width`` characters (a failure's reason)."""
    return "\n".join(textwrap.wrap(title, width))
