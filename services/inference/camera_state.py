"""What a stream of frames remembers per camera, and its ordering rule (the zenoh bridge and the gRPC
StreamMovingObjects keep one per camera; torch-free, so the bridge's bookkeeping loads without models)."""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class CameraState:
    """One camera's stream state: who publishes it (the bridge resets the state when that changes), the
    last processed frame (`.sequence`, `.timestamp`, ...) and its sequence number, and `extra`, owned by the
    processor (services.inference.camera_stream keeps the previous frame's encoding there)."""

    publisher_id: str | None = None
    last_sequence: int | None = None
    previous: object | None = None
    extra: dict = field(default_factory=dict)

    def verdict(self, sequence: int) -> str | None:
        """None when the frame numbered `sequence` comes next and is processed; "duplicate" (the same number
        again) or "out_of_order" (an older one) when it is dropped: sequence numbers only grow."""
        if self.last_sequence is None or sequence > self.last_sequence:
            return None
        return "duplicate" if sequence == self.last_sequence else "out_of_order"

    def advance(self, frame) -> None:
        """`frame` was processed: it is the previous frame of the next one."""
        self.previous, self.last_sequence = frame, int(frame.sequence)
