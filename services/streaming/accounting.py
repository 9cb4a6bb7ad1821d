"""Per-camera accounting of a bridge: every received sample ends in exactly one bucket.

    received = processed + dropped + malformed + processing_errors + pending

`pending` counts frames received but not yet in a final bucket: at most 2 per camera (one being
processed, the newest waiting in the camera's slot), so once the stream is idle the identity holds
without it. `dropped` counts frames skipped because a newer one arrived first (the bridge was behind),
plus duplicate and out-of-order frames; `malformed` counts payloads that did not decode, failed
validation, or that the processor refused as input (e.g. a timestamp before the previous frame's);
`processing_errors` counts frames whose processing failed for any other reason (a bug or a model error,
not the sender's mistake, so kept apart from `malformed`).
"""

from __future__ import annotations

import threading
from collections import deque
from dataclasses import dataclass, field

import numpy as np

LATENCY_WINDOW = 2048  # latencies kept per camera for percentiles
IDLE_EVICT_S = 300.0     # a bridge forgets a camera silent this long (services.streaming.bridge.Bridge)
MAX_CAMERAS = 256        # cameras a bridge tracks at once
RETIRED = "_retired"     # status entry holding the counters of forgotten cameras
TOO_MANY_CAMERAS = "_too_many_cameras"   # status entry counting the frames of cameras past MAX_CAMERAS
COUNTERS = ("received", "processed", "dropped", "malformed", "pending", "dropped_behind", "dropped_duplicate",
            "dropped_out_of_order", "processing_errors", "publisher_restarts", "scene_starts")


@dataclass
class CameraStats:
    received: int = 0
    processed: int = 0
    dropped: int = 0
    malformed: int = 0
    pending: int = 0
    dropped_behind: int = 0
    dropped_duplicate: int = 0
    dropped_out_of_order: int = 0
    processing_errors: int = 0
    publisher_restarts: int = 0
    scene_starts: int = 0  # processed frames answered as a scene's first: marked so by the source, or
    # following a frame so marked that was dropped behind (bridge.py)
    last_sequence: int | None = None
    latencies_ms: deque = field(default_factory=lambda: deque(maxlen=LATENCY_WINDOW))

    def to_json(self) -> dict:
        lat = np.asarray(self.latencies_ms, dtype=np.float64)
        pct = {f"p{q}": (float(np.percentile(lat, q)) if lat.size else None) for q in (50, 90, 99)}
        return {
            "received": self.received, "processed": self.processed, "dropped": self.dropped,
            "malformed": self.malformed, "pending": self.pending,
            "dropped_behind": self.dropped_behind, "dropped_duplicate": self.dropped_duplicate,
            "dropped_out_of_order": self.dropped_out_of_order, "processing_errors": self.processing_errors,
            "publisher_restarts": self.publisher_restarts, "scene_starts": self.scene_starts,
            "last_sequence": self.last_sequence,
            "latency_ms": {**pct, "count": int(lat.size)},
        }


class Accounting:
    """Thread-safe counters for all cameras (zenoh callback thread + worker thread + status queries)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._cameras: dict[str, CameraStats] = {}

    def _cam(self, camera: str) -> CameraStats:
        stats = self._cameras.get(camera)
        if stats is None:
            stats = self._cameras[camera] = CameraStats()
        return stats

    def update(self, camera: str, **increments: int) -> None:
        with self._lock:
            stats = self._cam(camera)
            for name, value in increments.items():
                setattr(stats, name, getattr(stats, name) + value)

    def set_last_sequence(self, camera: str, sequence: int) -> None:
        with self._lock:
            self._cam(camera).last_sequence = sequence

    def add_latency(self, camera: str, latency_ms: float) -> None:
        with self._lock:
            self._cam(camera).latencies_ms.append(latency_ms)

    def retire(self, camera: str, into: str) -> None:
        """Fold `camera`'s counters into the entry `into` (e.g. "_retired") and forget the camera: the totals
        stay, the per-camera entry (with its latency window) does not outlive the camera."""
        with self._lock:
            stats = self._cameras.pop(camera, None)
            if stats is None:
                return
            total = self._cam(into)
            for name in COUNTERS:
                setattr(total, name, getattr(total, name) + getattr(stats, name))

    def snapshot(self) -> dict[str, dict]:
        with self._lock:
            return {cam: stats.to_json() for cam, stats in self._cameras.items()}
