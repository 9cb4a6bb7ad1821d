"""The zenoh stream bridge: RGB-D frames in, egomotion and moving-object detections out.

Threads: zenoh delivers samples on its own callback thread; the callback only counts the sample
and parks it in its camera's one-frame slot (replacing — and counting as dropped — a frame the
worker had not reached yet), so a slow model never backs up zenoh and memory stays bounded. One
worker thread takes the newest frame of each camera in turn, decodes it, checks its sequence
(`CameraState.verdict`: duplicates and out-of-order frames are dropped, as gRPC StreamMovingObjects drops
them), runs the processor and publishes. Every received sample ends in exactly one accounting bucket
(see accounting.py): a payload that does not decode, or that the processor refuses as input, is malformed;
any other failure while processing counts as a processing error; nothing kills the worker.

Publisher restarts are recognised by the publisher id each camera puts in the sample attachment
(`pub=<id>`): a new id resets that camera's state instead of reading as out-of-order frames.
"""

from __future__ import annotations

import fnmatch
import json
import logging
import threading
import time
import uuid
from dataclasses import dataclass
from typing import Callable, Protocol

import zenoh

from services.inference.camera_state import CameraState
from services.streaming import keys
from services.streaming.accounting import Accounting
from services.streaming.session import ZenohOptions, open_session

log = logging.getLogger("n3dmap.bridge")


class MalformedFrame(ValueError):
    """A payload that does not decode into a valid frame."""


@dataclass
class Parked:
    """A received sample waiting for the worker."""

    payload: bytes
    attachment: bytes | None
    received_at: float


@dataclass
class Outputs:
    """What processing one frame produced: encoded payloads to publish (None = nothing)."""

    moving_objects: bytes | None
    egomotion: bytes | None


class FrameProcessor(Protocol):
    def decode(self, payload: bytes) -> object:
        """Payload bytes → decoded frame (raise MalformedFrame on bad input). Must expose
        `.camera_id`, `.sequence` and `.timestamp` (source time, seconds since the epoch)."""

    def process(self, camera: str, state: CameraState, frame: object) -> Outputs:
        """Run the models on `frame` given the camera's state (state.previous is the last frame); raise
        MalformedFrame for a frame it refuses as input."""

    # Optional: `prepare(camera, state)` runs on the worker when no frame waits (after a frame was
    # processed and state.previous set), and `stats() -> dict` adds to the status JSON.


def publisher_id_of(attachment: bytes | None) -> str | None:
    if not attachment:
        return None
    for part in attachment.decode("utf-8", "replace").split(";"):
        name, _, value = part.partition("=")
        if name.strip() == "pub":
            return value.strip()
    return None


class Bridge:
    """Subscribes to `n3dmap/<camera>/rgbd` for cameras matching `cameras` (a glob) and publishes
    `n3dmap/<camera>/moving_objects` and `n3dmap/<camera>/egomotion`."""

    def __init__(self, *, processor: FrameProcessor, zenoh_options: ZenohOptions, cameras: str = "*",
                 bridge_id: str | None = None, clock: Callable[[], float] = time.time) -> None:
        self.processor = processor
        self.zenoh_options = zenoh_options
        self.cameras = cameras
        self.bridge_id = bridge_id or uuid.uuid4().hex[:8]
        self.clock = clock
        self.accounting = Accounting()
        self._slots: dict[str, Parked] = {}
        self._states: dict[str, CameraState] = {}
        self._cond = threading.Condition()
        self._stopping = False
        self._worker: threading.Thread | None = None
        self._session: zenoh.Session | None = None
        self._declared: list = []
        self._publishers: dict[tuple[str, str], zenoh.Publisher] = {}
        self.started_at = 0.0

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> "Bridge":
        self.started_at = self.clock()
        self._session = open_session(self.zenoh_options)
        self._worker = threading.Thread(target=self._work, name="n3dmap-bridge-worker", daemon=True)
        self._worker.start()
        session = self._session
        self._declared.append(session.declare_subscriber(keys.rgbd("*"), self._on_sample))
        self._declared.append(session.declare_queryable(keys.bridge_status(self.bridge_id), self._on_status))
        self._declared.append(session.liveliness().declare_token(keys.bridge_token(self.bridge_id)))
        log.info("bridge %s listening on %s (cameras %r)", self.bridge_id, keys.rgbd("*"), self.cameras)
        return self

    def stop(self) -> None:
        """Undeclare first (no callback runs after), then stop the worker, then close the session."""
        for entity in reversed(self._declared):
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        self._declared.clear()
        with self._cond:
            self._stopping = True
            self._cond.notify_all()
        if self._worker is not None:
            self._worker.join(timeout=30)
        for pub in self._publishers.values():
            pub.undeclare()
        self._publishers.clear()
        if self._session is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> "Bridge":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- zenoh callbacks (zenoh thread: keep them short) ------------------------------------------
    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        camera = keys.camera_from_key(key)
        if camera is None:
            self.accounting.update("_unknown", received=1, malformed=1)
            log.warning("ignoring sample on unexpected key %s", key)
            return
        if not fnmatch.fnmatchcase(camera, self.cameras):
            # Not ours (another bridge serves it). Counted so that nothing disappears silently.
            self.accounting.update("_unmatched", received=1, dropped=1)
            return
        parked = Parked(payload=sample.payload.to_bytes(),
                        attachment=sample.attachment.to_bytes() if sample.attachment is not None else None,
                        received_at=self.clock())
        with self._cond:
            replaced = camera in self._slots
            self._slots[camera] = parked
            if replaced:
                self.accounting.update(camera, received=1, dropped=1, dropped_behind=1)
            else:
                self.accounting.update(camera, received=1, pending=1)
            self._cond.notify()

    def _on_status(self, query: zenoh.Query) -> None:
        query.reply(query.key_expr, json.dumps(self.status()))

    def status(self) -> dict:
        status = {"bridge_id": self.bridge_id, "cameras_pattern": self.cameras,
                  "uptime_s": round(self.clock() - self.started_at, 3), "cameras": self.accounting.snapshot()}
        stats = getattr(self.processor, "stats", None)
        if stats is not None:
            status["stages_ms"] = stats()  # per-stage model time percentiles (RuntimeProcessor)
        return status

    # -- worker ------------------------------------------------------------------------------------
    def _next(self) -> tuple[str, Parked] | None:
        with self._cond:
            while not self._slots and not self._stopping:
                self._cond.wait(timeout=0.5)
            if self._stopping:
                return None
            # Oldest-parked camera first, so one busy camera cannot starve the others.
            camera = min(self._slots, key=lambda c: self._slots[c].received_at)
            return camera, self._slots.pop(camera)

    def _work(self) -> None:
        while True:
            item = self._next()
            if item is None:
                return
            camera, parked = item
            try:
                self._handle(camera, parked)
            except Exception:  # the worker must survive anything a frame can cause
                log.exception("processing a frame of camera %s failed", camera)
                self.accounting.update(camera, processing_errors=1)
            finally:
                # Leaves `pending` only now that the frame sits in its final bucket, so the
                # identity received = processed + dropped + malformed + pending holds at every instant.
                self.accounting.update(camera, pending=-1)
            self._prepare_while_idle(camera)

    def _prepare_while_idle(self, camera: str) -> None:
        """Let the processor get ahead on the camera's next step (e.g. encode the frame just
        processed) — only when no frame is waiting, so it never delays one that is."""
        prepare = getattr(self.processor, "prepare", None)
        state = self._states.get(camera)
        if prepare is None or state is None:
            return
        with self._cond:
            if self._slots or self._stopping:
                return
        try:
            prepare(camera, state)
        except Exception:  # a failed preparation only costs the next step the same work again
            log.exception("preparing the next step of camera %s failed", camera)

    def _handle(self, camera: str, parked: Parked) -> None:
        try:
            frame = self.processor.decode(parked.payload)
        except MalformedFrame as e:
            log.warning("malformed frame from camera %s: %s", camera, e)
            self.accounting.update(camera, malformed=1)
            return
        if getattr(frame, "camera_id", camera) not in ("", camera):
            log.warning("frame on %s names camera %r; counted as malformed", keys.rgbd(camera), frame.camera_id)
            self.accounting.update(camera, malformed=1)
            return
        state = self._states.setdefault(camera, CameraState())
        publisher = publisher_id_of(parked.attachment)
        if publisher is not None and state.publisher_id is not None and publisher != state.publisher_id:
            log.info("camera %s: publisher restarted (%s → %s); state reset", camera, state.publisher_id, publisher)
            self.accounting.update(camera, publisher_restarts=1)
            state = self._states[camera] = CameraState()
        state.publisher_id = publisher
        seq = int(frame.sequence)
        kind = state.verdict(seq)
        if kind is not None:
            log.info("camera %s: %s frame %d (last %d)", camera, kind, seq, state.last_sequence)
            self.accounting.update(camera, dropped=1, **{f"dropped_{kind}": 1})
            return
        try:
            outputs = self.processor.process(camera, state, frame)
        except MalformedFrame as e:  # decoded, but the processor cannot answer it (e.g. its clock went back)
            log.warning("malformed frame %d from camera %s: %s", seq, camera, e)
            self.accounting.update(camera, malformed=1)
            return
        state.advance(frame)
        self._publish(keys.moving_objects(camera), outputs.moving_objects)
        self._publish(keys.egomotion(camera), outputs.egomotion)
        self.accounting.update(camera, processed=1)
        self.accounting.set_last_sequence(camera, seq)
        self.accounting.add_latency(camera, 1000.0 * (self.clock() - float(frame.timestamp)))

    def _publish(self, key: str, payload: bytes | None) -> None:
        if payload is None or self._session is None:
            return
        pub = self._publishers.get(("pub", key))
        if pub is None:
            pub = self._publishers[("pub", key)] = self._session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(payload)
