"""Reading Rerun recordings back in tests (shared by the viz unit tests and the CLI integration tests).

`rerun.chunk.RrdReader` streams the chunks an `.rrd` holds; `Recording` regroups them per entity and
component into rows sorted by a timeline, so a test can compare what was logged with what it expects.
"""

from __future__ import annotations

import os
import subprocess
from collections import defaultdict
from pathlib import Path

import numpy as np


class Recording:
    """Rows of an .rrd: `rows(entity, component, timeline)` -> [(time, value)] sorted by time (static rows
    have time None). Entity paths are given without the leading '/'; components as 'Archetype:field'."""

    def __init__(self, path: str | os.PathLike) -> None:
        from rerun.chunk import RrdReader

        self.path = Path(path)
        self._rows: dict[tuple[str, str], list[tuple[dict, object]]] = defaultdict(list)
        for chunk in RrdReader(str(path)).stream().to_chunks():
            entity = chunk.entity_path.lstrip("/")
            batch = chunk.to_record_batch().to_pydict()
            timelines = [t for t in chunk.timeline_names if t in batch]
            for name, column in batch.items():
                if ":" not in name:
                    continue
                for i, value in enumerate(column):
                    if value is None:
                        continue
                    self._rows[(entity, name)].append(({t: batch[t][i] for t in timelines}, value))

    def entities(self) -> set[str]:
        return {entity for entity, _ in self._rows}

    def components(self, entity: str) -> set[str]:
        return {c for e, c in self._rows if e == entity}

    def rows(self, entity: str, component: str, timeline: str | None = None) -> list[tuple[object, object]]:
        rows = self._rows.get((entity, component), [])
        out = [(times.get(timeline) if timeline else None, value) for times, value in rows]
        return sorted(out, key=lambda r: (r[0] is not None, r[0] if r[0] is not None else 0))

    def at(self, entity: str, component: str, timeline: str) -> dict:
        """{time: value} of a temporal component (the last row wins at a repeated time)."""
        return {t: v for t, v in self.rows(entity, component, timeline) if t is not None}

    def static(self, entity: str, component: str):
        values = [v for t, v in self.rows(entity, component) if t is None]
        assert values, f"no static {component} at {entity} in {self.path}"
        return values[-1]


def array(value, width: int | None = None) -> np.ndarray:
    """A batch value (list of fixed-size lists) -> N×width float64 array (N×0 when empty)."""
    arr = np.asarray(value, np.float64)
    return arr.reshape(-1, width) if width is not None else arr


def mat3(value) -> np.ndarray:
    """A Transform3D:mat3x3 / Pinhole value -> 3×3 (Rerun stores 3×3 matrices column-major)."""
    return np.asarray(value, np.float64).reshape(-1)[:9].reshape(3, 3).T


def yaw_from_quaternions(q) -> np.ndarray:
    """N×4 (x, y, z, w) rotations about Y -> N yaws (rad)."""
    q = array(q, 4)
    return 2.0 * np.arctan2(q[:, 1], q[:, 3])


def rerun_cli(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    """`rerun ARGS` with analytics off, as n3dmap starts it."""
    from services.viz.rerun_sdk import rerun_executable, viewer_env

    return subprocess.run([rerun_executable(), *args], env=viewer_env(), capture_output=True, text=True,
                          timeout=timeout)
