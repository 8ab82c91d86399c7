"""Matplotlib for writing PNG files from any process (no display): figures on the Agg canvas.

The schemes draw on :func:`figure`, a :class:`matplotlib.figure.Figure` with its own Agg
canvas: no ``pyplot`` (whose import, ~0.3–0.5 s, a run's picture need not pay) and no global
figure registry to close. Scripts may use :func:`pyplot`.

A run that will draw calls :func:`warm_up` before its solve where a core is idle: Matplotlib's
import (~0.3–0.5 s) and its first render's font loading then happen in a background thread on
that core while the solve runs (CasADi's calls release the GIL; the thread asks for it back
within :data:`WARM_UP_SWITCH_S`), and :func:`figure` waits for them.

Figures are laid out by Matplotlib's constrained layout, legends go below the axes
(:func:`legend_below`) and titles are wrapped to the figure's width (:func:`fit`), so no
text leaves the picture or covers its data. Axis labels name each component and its unit
through :func:`components`, the one place that reads them from a model.
"""

from __future__ import annotations

import sys
import textwrap
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

#: The unit an axis states where the model names none: the paper examples are
#: nondimensional.
NONDIMENSIONAL = "nondimensional"


@dataclass(frozen=True)
class Component:
    """One component's ``name`` (Matplotlib mathtext allowed) and ``unit`` for an axis."""

    name: str
    unit: str

    @property
    def label(self) -> str:
        """``name (unit)``, e.g. ``r (Mm)`` or ``x₁ (nondimensional)``."""
        return f"{self.name} ({self.unit})"


def subscript(number: int) -> str:
    """``number`` in Unicode subscript digits (x₁₂): plain text, not mathtext, whose parser
    costs a fresh process ~0.3 s to build on the first label that uses it."""
    return str(number).translate(str.maketrans("0123456789", "₀₁₂₃₄₅₆₇₈₉"))


def components(source: Any, kind: str, size: int, symbol: str) -> list[Component]:
    """Names and units of the ``size`` components of ``kind`` (``state``, ``control``,
    ``configuration`` (a mechanical system's q: its ``state_*`` members) or ``time``) of
    ``source``, a problem or model or a tuple of them searched in turn (e.g. ``(problem,
    model)``): the first one's ``<kind>_names`` and ``<kind>_units`` (``time_unit`` for the
    time; a sequence, or one string for all) that it has, the members
    :mod:`ocpar.models.labels` reads for the result files; else ``symbol`` with subscripts
    ₁, ₂, … (:func:`subscript`; ``symbol`` alone for one component); unit '1' (or none) is
    shown as :data:`NONDIMENSIONAL`."""
    sources = source if isinstance(source, tuple) else (source,)
    kinds = (kind, "state") if kind == "configuration" else (kind,)

    def first(*fields: str) -> Any:
        return next((value for s in sources for k in kinds for field in fields
                     if (value := getattr(s, f"{k}_{field}", None)) is not None), None)

    names, units = first("names"), first("unit" if kind == "time" else "units")
    if names is None:
        names = [symbol] if size == 1 else [symbol + subscript(i + 1) for i in range(size)]
    if units is None:
        units = [NONDIMENSIONAL] * size
    if isinstance(units, str):
        units = [units] * size
    units = [NONDIMENSIONAL if str(u) == "1" else str(u) for u in units]
    return [Component(str(n), u) for n, u in zip(names[:size], units[:size], strict=True)]


#: The interpreter's switch interval (s) while :func:`warm_up`'s thread runs: a thread that
#: wants the GIL waits this long before asking its holder for it (Python's default, 5 ms, would
#: hold the solve back after each of its CasADi calls while the import holds the GIL).
WARM_UP_SWITCH_S = 2e-4

#: The background thread of :func:`warm_up`, while one was started (at most one per process).
_warming: list[threading.Thread] = []


def warm_up() -> None:
    """Import Matplotlib's figure and Agg canvas and render one small figure with a title, a
    legend and tick labels (loading the fonts) in a background thread, once per process;
    :func:`figure` and :func:`pyplot` wait for it. Nothing is drawn for the caller: a
    picture drawn later finds Matplotlib imported and its fonts loaded."""
    if not _warming:
        _warming.append(threading.Thread(target=_warm, name="ocpar-plotting-warm-up",
                                         daemon=True))
        _warming[0].start()


def _warm() -> None:
    """:func:`warm_up`'s work: a 2 × 2 inch figure with one line, drawn and dropped."""
    interval = sys.getswitchinterval()
    sys.setswitchinterval(WARM_UP_SWITCH_S)
    try:
        fig = _new_figure(figsize=(2, 2))
        ax = fig.subplots()
        ax.plot([0.0, 1.0], [0.0, 1.0], label="t (s)")
        ax.set_title("warm-up", fontsize=10)
        ax.set_xlabel("x₁ (m)")
        fig.legend(loc="outside lower center", fontsize=8, frameon=False)
        fig.canvas.draw()
    except Exception:  # only a head start: the picture itself then says what fails
        pass
    finally:
        sys.setswitchinterval(interval)


def _wait_for_warm_up() -> None:
    """Wait until :func:`warm_up`'s thread (if any) is done (its figure is dropped)."""
    for thread in _warming:
        if thread is not threading.current_thread():
            thread.join()


def figure(**kwargs: Any) -> Any:
    """A :class:`matplotlib.figure.Figure` (``kwargs``: its options, e.g. ``figsize``;
    constrained layout unless ``layout`` says otherwise) on an Agg canvas of its own; draw
    with ``fig.subplots`` / ``fig.add_subplot``, write with :func:`save`."""
    _wait_for_warm_up()
    return _new_figure(**kwargs)


def _new_figure(**kwargs: Any) -> Any:
    """:func:`figure` without waiting for the warm-up (the warm-up's own)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(**({"layout": "constrained"} | kwargs))
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
    _wait_for_warm_up()
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


#: The pictures' resolution (dots per inch).
DPI = 120


def save(fig: Any, path: Path) -> Path:
    """Lay out ``fig`` (tight layout unless it has a layout engine), render it once at
    :data:`DPI` and write it to ``path`` as a PNG (fast zlib level 1, no metadata; ``savefig``
    would draw it a second time), then close it (where pyplot holds it)."""
    from PIL import Image

    if fig.get_layout_engine() is None:
        fig.tight_layout()
    fig.set_dpi(DPI)
    fig.canvas.draw()
    width, height = fig.canvas.get_width_height(physical=True)
    Image.frombuffer("RGBA", (width, height), fig.canvas.buffer_rgba(), "raw", "RGBA", 0,
                     1).save(path, format="png", compress_level=1)
    if (plt := sys.modules.get("matplotlib.pyplot")) is not None:
        plt.close(fig)
    return Path(path)


def wrapped(title: str, width: int = 70) -> str:
    """``title`` broken into lines of at most ``width`` characters (a failure's reason)."""
    return "\n".join(textwrap.wrap(title, width))


def fit(title: str, fig: Any, fontsize: float, share: float = 1.0) -> str:
    """``title`` wrapped (at its own line breaks too) to ``share`` of ``fig``'s width at
    ``fontsize`` points (an average character taken as 0.6 em)."""
    width = max(20, int(share * fig.get_figwidth() * 72 / (0.6 * fontsize)) - 2)
    return "\n".join(wrapped(line, width) or line for line in title.split("\n"))


def legend_below(fig: Any, axes: Sequence[Any], fontsize: float = 8) -> Any:
    """One legend of every labelled artist of ``axes`` (first label wins), below the axes,
    outside them (constrained layout makes room): it covers no data. As many columns as
    the longest label lets fit in the figure's width; labels too long for it are wrapped."""
    handles: dict[str, Any] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            handles.setdefault(label, handle)
    em = 0.6 * fontsize / 72                    # an average character's width (inches)
    room = fig.get_figwidth() - 0.8             # less the handle and the padding (inches)
    labels = [wrapped(label, max(20, int(room / em))) for label in handles]
    longest = max((len(line) for label in labels for line in label.split("\n")), default=1)
    columns = max(1, min(len(labels), int(fig.get_figwidth() // (longest * em + 0.8))))
    return fig.legend(list(handles.values()), labels, loc="outside lower center",
                      ncols=columns, fontsize=fontsize, frameon=False)
