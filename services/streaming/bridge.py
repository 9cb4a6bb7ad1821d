"""The zenoh stream bridge: RGB-D frames in, egomotion and moving-object detections out.

Threads: zenoh delivers samples on its own callback thread; the callback only counts the sample
and parks it in its camera's one-frame slot (replacing — and counting as dropped — a frame the
worker had not reached yet), so a slow model never backs up zenoh and memory stays bounded. One
worker thread takes the newest frame of each camera in turn, decodes it, checks its sequence
(`CameraState.verdict`: duplicates and out-of-order frames are dropped, as gRPC StreamMovingObjects drops
them), runs the processor and publishes. Every received sample ends in exactly one accounting bucket
(see accounting.py): a payload that does not decode, or that the processor refuses as input, is malformed;
any other failure while processing counts as a processing error; nothing kills the worker.

Look-ahead (on by default when the processor has `encode_ahead`): a second thread decodes each parked
frame and makes its own-frame work (`encode_ahead`: nothing in it depends on another frame) while the
worker still runs the step before, so the two cores share a frame's work: the worker's step is left with
the pair work only. The look-ahead also hands the processor the look-ahead of the frame the worker took
last for that camera (the frame the step will most likely pair this one with), so that it can make the
pair's egomotion too; the processor checks that the pairing held before using it. The worker takes a
frame only once the look-ahead has finished with it, and does the work itself only where the look-ahead
failed; a frame replaced in its slot before the worker reached it is dropped as before, and its
look-ahead work is wasted, never published. Why: at the small preset the
frame's own work (egomotion volume and encoding, the flow module's encoding of it, its depth evidence)
was about a third of a step, and one core could not keep up with a 10 Hz camera.

A cut is never paired across: a frame replaced in its slot that started a scene (`scene_start`) passes the
mark on to the frame that replaced it, which is then answered like a camera's first frame (else, with the
cut's first frame dropped behind, the next frame would pair with the last frame of the scene before); a
frame carrying a cut that is then not processed (malformed, refused, failed) passes it on to the camera's
next processed frame.

Publisher restarts are recognised by the publisher id each camera puts in the sample attachment
(`pub=<id>`): a new id resets that camera's state instead of reading as out-of-order frames.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import logging
import threading
import time
import uuid
from dataclasses import dataclass, field
from typing import Callable, Protocol

import zenoh

from services.inference.camera_state import CameraState
from services.streaming import keys
from services.streaming.accounting import IDLE_EVICT_S, MAX_CAMERAS, RETIRED, TOO_MANY_CAMERAS, Accounting
from services.streaming.session import ZenohOptions, open_session

log = logging.getLogger("n3dmap.bridge")


class MalformedFrame(ValueError):
    """A payload that does not decode into a valid frame."""


@dataclass
class Parked:
    """A received sample waiting for the worker; the look-ahead thread fills the last four fields."""

    payload: bytes
    attachment: bytes | None
    received_at: float
    claimed: bool = False                    # the look-ahead thread took it (set under the bridge's lock)
    done: threading.Event = field(default_factory=threading.Event)  # set when the look-ahead finished
    frame: object | None = None              # the decoded frame
    malformed: MalformedFrame | None = None  # or why it does not decode
    ahead: object | None = None              # processor.encode_ahead(frame), None if it failed
    follows_cut: bool = False                # a frame it replaced started a scene: this one starts it now


@dataclass
class Outputs:
    """What processing one frame produced: encoded payloads to publish (None = nothing)."""

    moving_objects: bytes | None
    egomotion: bytes | None


class FrameProcessor(Protocol):
    def decode(self, payload: bytes) -> object:
        """Payload bytes → decoded frame (raise MalformedFrame on bad input). Must expose
        `.camera_id`, `.sequence` and `.timestamp` (source time, seconds since the epoch), and may expose
        `.scene_start`."""

    def process(self, camera: str, state: CameraState, frame: object) -> Outputs:
        """Run the models on `frame` given the camera's state (state.previous is the last frame); raise
        MalformedFrame for a frame it refuses as input."""

    # Optional: `prepare(camera, state)` runs on the worker when no frame waits (after a frame was
    # processed and state.previous set); `encode_ahead(frame, previous) -> object` runs on the look-ahead
    # thread (previous: the result for the frame the worker took last of that camera, or None) and its
    # result reaches `process(camera, state, frame, ahead)`; `stats() -> dict` adds to the status JSON;
    # `starts_scene(payload) -> bool` reads a payload's scene_start flag without a full decode (else the
    # bridge decodes a replaced frame to read it).


def mark_scene_start(frame: object) -> object:
    """`frame` with scene_start set: a copy of a dataclass (View is frozen), else set in place."""
    if dataclasses.is_dataclass(frame):
        return dataclasses.replace(frame, scene_start=True)
    frame.scene_start = True
    return frame


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
                 bridge_id: str | None = None, clock: Callable[[], float] = time.monotonic,
                 lookahead: bool = True, idle_evict_s: float = IDLE_EVICT_S, max_cameras: int = MAX_CAMERAS) -> None:
        """lookahead: run the processor's `encode_ahead` on a second thread (see the module doc); ignored
        for a processor without it. idle_evict_s: a camera that sent nothing for this long is forgotten (its
        state — the previous frame and its encoding, several MB — freed, its counters folded into the status's
        "_retired" entry); when it comes back its first frame pairs with nothing, as a scene start.
        max_cameras: cameras tracked at once; a frame of one more is dropped and counted under
        "_too_many_cameras" (camera ids that change — hostname-pid, a flood of keys — would otherwise grow the
        bridge's memory without bound). clock: when samples arrive, for idle eviction, fair order and uptime —
        monotonic, so that a wall-clock step (NTP, a suspended host) cannot evict live cameras; latency compares
        frames' wall-clock timestamps with time.time()."""
        self.processor = processor
        self.zenoh_options = zenoh_options
        self.cameras = cameras
        self.bridge_id = bridge_id or uuid.uuid4().hex[:8]
        self.clock = clock
        self.accounting = Accounting()
        self.idle_evict_s, self.max_cameras = idle_evict_s, max_cameras
        self._last_seen: dict[str, float] = {}   # per tracked camera: when its latest sample arrived (under _cond)
        self._slots: dict[str, Parked] = {}
        self._states: dict[str, CameraState] = {}
        self._cond = threading.Condition()
        self._stopping = False
        self._worker: threading.Thread | None = None
        self._lookahead: threading.Thread | None = None
        self._taken: dict[str, Parked] = {}  # per camera: the frame the worker took last
        # Cameras whose latest cut reached no processed frame (the frame carrying it was malformed, refused or
        # failed): their next processed frame starts the scene. Worker thread only.
        self._pending_cut: set[str] = set()
        self.lookahead = lookahead and hasattr(processor, "encode_ahead")
        self._session: zenoh.Session | None = None
        self._declared: list = []
        self._publishers: dict[tuple[str, str], zenoh.Publisher] = {}
        self.started_at = 0.0

    # -- lifecycle -------------------------------------------------------------------------------
    def start(self) -> "Bridge":
        """Open the session, start the threads, declare the subscriber, status queryable and token; if any of it
        fails, what was started is stopped again before the error is raised (a caller's `with` never began)."""
        self.started_at = self.clock()
        self._session = open_session(self.zenoh_options)
        try:
            self._worker = threading.Thread(target=self._work, name="n3dmap-bridge-worker", daemon=True)
            self._worker.start()
            if self.lookahead:
                self._lookahead = threading.Thread(target=self._look_ahead, name="n3dmap-bridge-lookahead",
                                                   daemon=True)
                self._lookahead.start()
            session = self._session
            self._declared.append(session.declare_subscriber(keys.rgbd("*"), self._on_sample))
            self._declared.append(session.declare_queryable(keys.bridge_status(self.bridge_id), self._on_status))
            self._declared.append(session.liveliness().declare_token(keys.bridge_token(self.bridge_id)))
        except BaseException:
            self.stop()
            raise
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
        for thread in (self._worker, self._lookahead):
            if thread is not None:
                thread.join(timeout=30)
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
            if camera not in self._last_seen and len(self._last_seen) >= self.max_cameras:
                self.accounting.update(TOO_MANY_CAMERAS, received=1, dropped=1)
                return
            self._last_seen[camera] = parked.received_at
            replaced = self._slots.get(camera)
            if replaced is not None:
                parked.follows_cut = replaced.follows_cut or self._starts_scene(replaced)
            self._slots[camera] = parked
            if replaced is not None:
                self.accounting.update(camera, received=1, dropped=1, dropped_behind=1)
            else:
                self.accounting.update(camera, received=1, pending=1)
            self._cond.notify_all()  # the worker and the look-ahead thread both wait on it

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
        """The next frame for the worker. With look-ahead, only a frame the look-ahead thread has finished:
        the worker never races it for a new frame (the two would then run one frame's work in series and
        leave a core idle)."""
        with self._cond:
            while True:
                if self._stopping:
                    return None
                self._evict_idle()
                ready = [c for c, p in self._slots.items() if self._ready(p)]
                if ready:
                    break
                self._cond.wait(timeout=0.5)
            # Oldest-parked camera first, so one busy camera cannot starve the others.
            camera = min(ready, key=lambda c: self._slots[c].received_at)
            parked = self._slots.pop(camera)
            self._taken[camera] = parked
        return camera, parked

    def _evict_idle(self) -> None:
        """Forget the cameras idle for idle_evict_s and with no frame parked (under _cond). It runs on the worker
        thread between two frames, so no frame is being handled then, and the worker — the one thread that touches
        _states and _publishers — only ever takes frames the look-ahead has finished."""
        now = self.clock()
        for camera, seen in list(self._last_seen.items()):
            if now - seen < self.idle_evict_s or camera in self._slots:
                continue
            del self._last_seen[camera]
            self._states.pop(camera, None)
            self._taken.pop(camera, None)
            for key in (keys.moving_objects(camera), keys.egomotion(camera)):   # its declarations on the router too
                publisher = self._publishers.pop(("pub", key), None)
                if publisher is not None:
                    publisher.undeclare()
            self._pending_cut.discard(camera)
            self.accounting.retire(camera, into=RETIRED)
            log.info("camera %s idle for %.0f s: its state is freed", camera, now - seen)

    def _ready(self, parked: Parked) -> bool:
        """Whether the worker may take `parked`: always without look-ahead, else once the look-ahead is done."""
        return not self.lookahead or parked.done.is_set()

    def _look_ahead(self) -> None:
        """Decode and encode the newest unclaimed parked frame, beside the worker (see the module doc)."""
        while True:
            with self._cond:
                while not self._stopping and not any(not p.claimed for p in self._slots.values()):
                    self._cond.wait(timeout=0.5)
                if self._stopping:
                    return
                camera, parked = max(((c, p) for c, p in self._slots.items() if not p.claimed),
                                     key=lambda item: item[1].received_at)
                parked.claimed = True
                before = self._taken.get(camera)
            try:
                self._decode(parked)
                if parked.frame is not None:
                    # `before` was made by this thread (then it is done) or decoded by the worker (no ahead).
                    previous = before.ahead if before is not None and before.done.is_set() else None
                    parked.ahead = self.processor.encode_ahead(parked.frame, previous)
            except Exception:  # the worker then does the work itself; nothing is lost
                log.exception("look-ahead encoding failed; the worker will redo it")
            finally:
                with self._cond:
                    parked.done.set()
                    self._cond.notify_all()

    def _carry_cut(self, camera: str, parked: Parked) -> None:
        """`parked` will not be processed: a cut it carries passes to the camera's next processed frame."""
        if parked.follows_cut or self._starts_scene(parked):
            self._pending_cut.add(camera)

    def _starts_scene(self, parked: Parked) -> bool:
        """Whether `parked` (about to go unprocessed) starts a scene: its decoded frame's flag, else the flag
        read from its payload (`starts_scene`, which reads it even from a frame that fails validation), else a
        decode's; a payload whose flag cannot be read starts none. On zenoh's thread (a replaced frame) it is
        a flag read, not a decode, when the processor can."""
        frame = parked.frame
        if frame is not None:
            return bool(getattr(frame, "scene_start", False))
        starts_scene = getattr(self.processor, "starts_scene", None)
        try:
            if starts_scene is not None:
                return bool(starts_scene(parked.payload))
            return bool(getattr(self.processor.decode(parked.payload), "scene_start", False))
        except Exception:  # malformed: it would not have been processed either
            return False

    def _decode(self, parked: Parked) -> None:
        try:
            frame = self.processor.decode(parked.payload)
        except MalformedFrame as e:
            parked.malformed = e
            return
        if parked.follows_cut and not getattr(frame, "scene_start", False):
            frame = mark_scene_start(frame)
        parked.frame = frame

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
        processed) — only when no frame is ready for the worker, so it never delays one that is (with
        look-ahead, a frame still being encoded by the look-ahead thread is not ready)."""
        prepare = getattr(self.processor, "prepare", None)
        state = self._states.get(camera)
        if prepare is None or state is None:
            return
        with self._cond:
            if self._stopping or any(self._ready(p) for p in self._slots.values()):
                return
        try:
            prepare(camera, state)
        except Exception:  # a failed preparation only costs the next step the same work again
            log.exception("preparing the next step of camera %s failed", camera)

    def _handle(self, camera: str, parked: Parked) -> None:
        if parked.frame is None and parked.malformed is None:
            self._decode(parked)  # not decoded yet (or the look-ahead failed): here, where errors are counted
        if parked.malformed is not None:
            log.warning("malformed frame from camera %s: %s", camera, parked.malformed)
            self.accounting.update(camera, malformed=1)
            self._carry_cut(camera, parked)
            return
        frame = parked.frame
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
            self._pending_cut.discard(camera)  # a new publisher's first frame pairs with nothing anyway
        state.publisher_id = publisher
        seq = int(frame.sequence)
        kind = state.verdict(seq)
        if kind is not None:
            log.info("camera %s: %s frame %d (last %d)", camera, kind, seq, state.last_sequence)
            self.accounting.update(camera, dropped=1, **{f"dropped_{kind}": 1})
            return
        if camera in self._pending_cut and not getattr(frame, "scene_start", False):
            frame = parked.frame = mark_scene_start(frame)  # a copy for a View: the look-ahead's work is redone
        try:
            if parked.ahead is not None:
                outputs = self.processor.process(camera, state, frame, parked.ahead)
            else:
                outputs = self.processor.process(camera, state, frame)
        except MalformedFrame as e:  # decoded, but the processor cannot answer it (e.g. its clock went back)
            log.warning("malformed frame %d from camera %s: %s", seq, camera, e)
            self.accounting.update(camera, malformed=1)
            self._carry_cut(camera, parked)
            return
        except Exception:
            self._carry_cut(camera, parked)
            raise
        self._pending_cut.discard(camera)
        state.advance(frame)
        self._publish(keys.moving_objects(camera), outputs.moving_objects)
        self._publish(keys.egomotion(camera), outputs.egomotion)
        self.accounting.update(camera, processed=1, scene_starts=int(bool(getattr(frame, "scene_start", False))))
        self.accounting.set_last_sequence(camera, seq)
        self.accounting.add_latency(camera, 1000.0 * (time.time() - float(frame.timestamp)))

    def _publish(self, key: str, payload: bytes | None) -> None:
        if payload is None or self._session is None:
            return
        pub = self._publishers.get(("pub", key))
        if pub is None:
            pub = self._publishers[("pub", key)] = self._session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(payload)
