"""Options of a gRPC StreamMovingObjects call, read from its metadata (torch-free).

A stream's request is a stream of Frames, so options that hold for the whole call travel as call
metadata, the way gRPC carries its own per-call settings. They are the zenoh bridge's placement options
(`n3dmap stream bridge --level --level-ahead M --ground-y Y`, services.inference.camera_stream.MovingStream):

  n3dmap-level        "1" / "true": boxes in each frame's camera levelled to gravity (frame "level",
                      Detections.world_T_frame its pose); "0" / "false" (the default): the camera (frame "ref")
  n3dmap-level-ahead  metres (≥ 0): the levelled map's centre that far ahead along the heading
  n3dmap-ground-y     the world's ground height (Y down): the levelled map's centre at the preset's height
                      above it

A malformed value, or a placement without n3dmap-level, is an InvalidInput naming the key (the server
answers INVALID_ARGUMENT before reading any frame). Unknown keys are left alone (they may be the
transport's or the caller's own).
"""

from __future__ import annotations

import math
from typing import Iterable

from services.inference.errors import InvalidInput

LEVEL_KEY = "n3dmap-level"
LEVEL_AHEAD_KEY = "n3dmap-level-ahead"
GROUND_Y_KEY = "n3dmap-ground-y"
_TRUE, _FALSE = ("1", "true"), ("0", "false")


def stream_options(metadata: Iterable[tuple[str, str | bytes]] | None) -> dict:
    """Call metadata (key, value) pairs -> MovingStream's keyword options {level, level_ahead, ground_y}."""
    values: dict[str, str] = {}
    for key, value in metadata or ():
        if key in (LEVEL_KEY, LEVEL_AHEAD_KEY, GROUND_Y_KEY):
            if key in values:
                raise InvalidInput(f"metadata {key}", "given more than once")
            values[key] = value.decode() if isinstance(value, bytes) else str(value)
    level_text = values.get(LEVEL_KEY, "0").strip().lower()
    if level_text not in _TRUE + _FALSE:
        raise InvalidInput(f"metadata {LEVEL_KEY}", f"must be 1, true, 0 or false, got {values[LEVEL_KEY]!r}")
    options = {"level": level_text in _TRUE}
    if LEVEL_AHEAD_KEY in values:
        options["level_ahead"] = _number(LEVEL_AHEAD_KEY, values[LEVEL_AHEAD_KEY])
        if options["level_ahead"] < 0:
            raise InvalidInput(f"metadata {LEVEL_AHEAD_KEY}", f"must be ≥ 0 metres, got {values[LEVEL_AHEAD_KEY]}")
    if GROUND_Y_KEY in values:
        options["ground_y"] = _number(GROUND_Y_KEY, values[GROUND_Y_KEY])
    placed = [k for k in (LEVEL_AHEAD_KEY, GROUND_Y_KEY) if k in values]
    if placed and not options["level"]:
        raise InvalidInput(f"metadata {placed[0]}", f"places the levelled map: it needs {LEVEL_KEY}: 1")
    return options


def stream_metadata(*, level: bool = False, level_ahead: float | None = None,
                    ground_y: float | None = None) -> tuple[tuple[str, str], ...]:
    """The client's side: options -> metadata pairs (none for the defaults)."""
    pairs = []
    if level:
        pairs.append((LEVEL_KEY, "1"))
    if level_ahead is not None:
        pairs.append((LEVEL_AHEAD_KEY, repr(float(level_ahead))))
    if ground_y is not None:
        pairs.append((GROUND_Y_KEY, repr(float(ground_y))))
    return tuple(pairs)


def _number(key: str, text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InvalidInput(f"metadata {key}", f"must be a number, got {text!r}") from None
    if not math.isfinite(value):
        raise InvalidInput(f"metadata {key}", f"must be finite, got {text!r}")
    return value
