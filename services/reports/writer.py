"""The one report writer every `n3dmap eval KIND` uses.

A `Report` collects, in order, markdown sections (headings, paragraphs, tables) and figures, plus a
nested metrics dict; `write(out_dir)` creates
    out_dir/report.md      the sections, with tables as markdown and figures as image links
    out_dir/metrics.json   {"kind", "created", "bundle", "data", "metrics": {...}, "settings": {...}}
    out_dir/*.png          one file per figure (matplotlib, Agg backend, no display needed)
Non-finite floats are written to JSON as null (JSON has no NaN).
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


def json_safe(value: Any) -> Any:
    """JSON-safe copy: NaN/inf -> None, numpy scalars/arrays -> Python, tuples -> lists."""
    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "tolist"):
        return json_safe(value.tolist())
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    return value


def format_number(value: Any, digits: int = 3) -> str:
    if value is None:
        return "–"
    if isinstance(value, float):
        if not math.isfinite(value):
            return "–"
        return f"{value:.{digits}f}" if abs(value) >= 10 ** -digits or value == 0 else f"{value:.2e}"
    return str(value)


@dataclass
class Report:
    kind: str
    title: str
    bundle: str | None = None
    data: str | None = None
    settings: dict = field(default_factory=dict)
    metrics: dict = field(default_factory=dict)
    _blocks: list = field(default_factory=list)
    _figures: list = field(default_factory=list)

    def heading(self, text: str, level: int = 2) -> None:
        self._blocks.append("#" * level + " " + text)

    def text(self, paragraph: str) -> None:
        self._blocks.append(paragraph.strip())

    def table(self, header: list[str], rows: list[list[Any]], *, digits: int = 3) -> None:
        lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
        for row in rows:
            lines.append("| " + " | ".join(format_number(v, digits) for v in row) + " |")
        self._blocks.append("\n".join(lines))

    def figure(self, name: str, fig, caption: str) -> None:
        """Add a matplotlib figure saved as `<name>.png` (name: letters, digits, _ and -)."""
        if not re.fullmatch(r"[A-Za-z0-9_-]+", name):
            raise ValueError(f"figure name must be [A-Za-z0-9_-]+, got {name!r}")
        self._figures.append((name, fig))
        self._blocks.append(f"![{caption}]({name}.png)\n\n*{caption}*")

    def write(self, out_dir: str | os.PathLike) -> Path:
        """Write report.md, metrics.json and the PNGs into out_dir (created); returns the path."""
        import matplotlib.pyplot as plt

        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        for name, fig in self._figures:
            fig.savefig(out / f"{name}.png", dpi=100, bbox_inches="tight")
            plt.close(fig)
        head = [f"# {self.title}", ""]
        if self.bundle:
            head.append(f"- bundle: `{self.bundle}`")
        if self.data:
            head.append(f"- data: `{self.data}`")
        for k, v in self.settings.items():
            head.append(f"- {k}: {format_number(v) if isinstance(v, float) else v}")
        (out / "report.md").write_text("\n".join(head) + "\n\n" + "\n\n".join(self._blocks) + "\n")
        payload = {"kind": self.kind, "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
                   "bundle": self.bundle, "data": self.data, "settings": self.settings, "metrics": self.metrics}
        (out / "metrics.json").write_text(json.dumps(json_safe(payload), indent=2, sort_keys=False) + "\n")
        return out
