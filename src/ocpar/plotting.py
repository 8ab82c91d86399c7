"""Matplotlib for writing PNG files from any process (no display): the Agg backend."""

from __future__ import annotations

import textwrap
from pathlib import Path
from types import ModuleType


def pyplot() -> ModuleType:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (imported on first use)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: Path) -> Path:
    """Lay out ``fig``, write it to ``path`` as a 120-dpi PNG and close it."""
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    pyplot().close(fig)
    return Path(path)


def wrapped(title: str, width: int = 70) -> str:
    """``title`` broken into lines of at most ``width`` characters (a failure's reason)."""
    return "\n".join(textwrap.wrap(title, width))
