"""What every scheme's result shares: its superstep count and its ``result.json``."""

from __future__ import annotations

import json
from pathlib import Path

from ocpar.bsp import SuperstepTrace


class RunResult:
    """Mixin for a scheme's result dataclass, which provides ``trace`` and ``to_dict()``."""

    trace: list[SuperstepTrace]

    def to_dict(self) -> dict:  # pragma: no cover - provided by each scheme
        raise NotImplementedError

    @property
    def supersteps(self) -> int:
        return len(self.trace)

    def write_json(self, path: Path) -> Path:
        """Write :meth:`to_dict` as JSON to ``path`` (a file, or a directory → result.json)."""
        path = Path(path)
        if path.is_dir():
            path = path / "result.json"
        path.write_text(json.dumps(self.to_dict()))
        return path
