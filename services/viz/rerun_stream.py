"""The live stream as a Rerun recording (`n3dmap stream view`): frames, detections and egomotion of one
camera, on the `frame` timeline (the camera's sequence numbers) and the `source_time` timeline (the
frames' source timestamps), in `world` (entity paths in rerun_paths).

- Each frame: the camera's pose world_T_cam (as the frame carries it), its Pinhole, RGB and depth
  (a DepthImage the viewer back-projects), and the trajectory of camera centres so far.
- Each Detections message (one per frame the bridge processed, the first frame's empty one included):
  its frame `ref` (world_T_frame, the camera at the pair's first frame) holding the moving-object boxes
  (red, labelled with score and speed) and their velocities as arrows of the distance covered in one
  second; plus the end-to-end latency (source timestamp to receipt) as a scalar.
- Each egomotion message (cam0_T_cam1 of the same pair): the trajectory the bridge's egomotion gives
  when chained, started at the given pose of the first frame it covers — drawn beside the given one,
  so estimation drift is visible.

A publisher restart (the sequence going back) starts both trajectories afresh.
"""

from __future__ import annotations

import numpy as np

from services.viz import rerun_paths as paths
from services.viz.rerun_archetypes import boxes3d, pinhole, transform
from services.viz.rerun_blueprints import stream_blueprint

DEFAULT_TRAJECTORY_POINTS = 2000  # the newest camera centres drawn (the strip is logged whole per frame)


class StreamRecorder:
    """Logs one camera's stream to a Rerun recording stream. Not thread-safe: call from one thread."""

    def __init__(self, *, recording, trajectory_points: int = DEFAULT_TRAJECTORY_POINTS) -> None:
        from services.viz.rerun_sdk import require_rerun

        self.rr = require_rerun()
        self.rec = recording
        self.trajectory_points = trajectory_points
        self.frames = self.detections = self.egomotions = 0
        self._last_frame_sequence: int | None = None
        self._centres: list[np.ndarray] = []                # given camera centres, oldest first
        self._estimated: dict[int, np.ndarray] = {}         # sequence -> chained world_T_cam (4×4)
        self._estimated_centres: list[np.ndarray] = []
        self._last_detections: int | None = None            # sequence of the newest Detections
        self._previous_detections: int | None = None        # ... and of the one before (the pair's first frame)
        self._pair_world_T_frame: np.ndarray | None = None  # world_T_frame of the newest Detections
        self.rec.send_blueprint(stream_blueprint())
        self.rec.log(paths.WORLD, self.rr.ViewCoordinates.RDF, static=True)
        self._log_chase_eye()

    def _log_chase_eye(self, *, back: float = 12.0, up: float = 5.0, pitch_deg: float = 15.0) -> None:
        """A virtual camera `back` m behind and `up` m above the stream's camera, pitched down, in its frame
        (static: it moves with the camera); the default 3D view looks through it."""
        rr = self.rr
        a = np.deg2rad(pitch_deg)
        pose = np.eye(4)
        # Rotation about X by -pitch turns +Z (forward) down toward +Y (down): R = [[1,0,0],[0,c,s],[0,-s,c]]ᵀ
        pose[:3, :3] = [[1, 0, 0], [0, np.cos(a), np.sin(a)], [0, -np.sin(a), np.cos(a)]]
        pose[:3, 3] = [0.0, -up, -back]
        self.rec.log(paths.STREAM_EYE, transform(rr, pose), static=True)
        k = np.array([[640.0, 0, 640, 0], [0, 640.0, 360, 0], [0, 0, 1, 0], [0, 0, 0, 1]])  # 90° wide, 16:9
        self.rec.log(paths.STREAM_EYE, pinhole(rr, k, height=720, width=1280, image_plane_distance=0.5), static=True)

    def _at(self, sequence: int, timestamp: float | None) -> None:
        self.rec.set_time(paths.FRAME, sequence=int(sequence))
        if timestamp:
            self.rec.set_time(paths.SOURCE_TIME, timestamp=float(timestamp))

    def log_frame(self, *, sequence: int, timestamp: float, rgb: np.ndarray, depth: np.ndarray,
                  pix_T_cam: np.ndarray, world_T_cam: np.ndarray | None) -> None:
        """One frame: rgb H×W×3 uint8, depth H×W metres (0 = none), pix_T_cam 4×4, world_T_cam 4×4 or None."""
        rr = self.rr
        if self._last_frame_sequence is not None and sequence <= self._last_frame_sequence:
            self._restart()
        self._last_frame_sequence = int(sequence)
        self._at(sequence, timestamp)
        H, W = depth.shape
        if world_T_cam is not None:
            self.rec.log(paths.STREAM_CAMERA, transform(rr, world_T_cam))
            self._centres = (self._centres + [np.asarray(world_T_cam, np.float64)[:3, 3]])[-self.trajectory_points:]
            self.rec.log(paths.TRAJECTORY, rr.LineStrips3D([np.array(self._centres, np.float32)],
                                                           colors=[paths.TRAJECTORY_COLOR]))
        self.rec.log(paths.STREAM_IMAGE, pinhole(rr, pix_T_cam, height=H, width=W))
        self.rec.log(paths.STREAM_IMAGE, rr.Image(rgb, color_model="RGB"))
        self.rec.log(paths.STREAM_IMAGE, rr.DepthImage(depth, meter=1.0))
        self.frames += 1

    def log_detections(self, *, sequence: int, timestamp: float, boxes: np.ndarray, scores: np.ndarray,
                       velocities: np.ndarray, world_T_frame: np.ndarray | None, received_at: float) -> None:
        """One Detections message: boxes N×7 in its frame `ref`, scores N, velocities N×3 (m/s, in ref),
        world_T_frame 4×4 (None: drawn in world as if ref were world), received_at (epoch seconds)."""
        rr = self.rr
        self._at(sequence, timestamp)
        # Logged every time (identity when the message names no pose), so no earlier pose lingers.
        self.rec.log(paths.DETECTIONS_FRAME, transform(rr, np.eye(4) if world_T_frame is None else world_T_frame))
        boxes = np.asarray(boxes, np.float32).reshape(-1, 7)
        velocities = np.asarray(velocities, np.float32).reshape(-1, 3)
        speeds = np.linalg.norm(velocities, axis=1)
        self.rec.log(paths.DETECTIONS, boxes3d(rr, boxes, colors=paths.MOVING_BOX,
                                               labels=[f"{s:.2f}, {v:.1f} m/s" for s, v in zip(scores, speeds)]))
        self.rec.log(paths.VELOCITIES, rr.Arrows3D(origins=boxes[:, :3], vectors=velocities * 1.0,  # 1 s of motion
                                                   colors=[paths.MOVING_BOX]))
        if timestamp:
            self.rec.log(paths.LATENCY, rr.Scalars(1000.0 * (received_at - timestamp)))
        self._previous_detections, self._last_detections = self._last_detections, int(sequence)
        self._pair_world_T_frame = None if world_T_frame is None else np.asarray(world_T_frame, np.float64)
        self.detections += 1

    def log_egomotion(self, *, cam0_T_cam1: np.ndarray) -> None:
        """The egomotion of the newest Detections' pair (the bridge publishes it right after them):
        chains est_world_T_cam(this frame) = est_world_T_cam(pair's first frame) · cam0_T_cam1."""
        if self._last_detections is None:
            return  # nothing to attach it to (the viewer joined mid-stream)
        start = self._estimated.get(self._previous_detections)
        if start is None:  # a new chain, at the first frame's given pose
            start = self._pair_world_T_frame if self._pair_world_T_frame is not None else np.eye(4)
            self._estimated_centres = [start[:3, 3]]
        pose = start @ np.asarray(cam0_T_cam1, np.float64)
        self._estimated = {self._last_detections: pose}  # only the newest is ever chained from
        self._estimated_centres = (self._estimated_centres + [pose[:3, 3]])[-self.trajectory_points:]
        self.rec.set_time(paths.FRAME, sequence=self._last_detections)
        self.rec.log(paths.TRAJECTORY_EGO, self.rr.LineStrips3D([np.array(self._estimated_centres, np.float32)],
                                                                colors=[paths.TRAJECTORY_EGO_COLOR]))
        self.egomotions += 1

    def _restart(self) -> None:
        self._centres, self._estimated_centres, self._estimated = [], [], {}
        self._last_detections = self._previous_detections = None
