"""Evaluation entries as a Rerun recording (`n3dmap eval moving|flow|detection ... --rerun FILE.rrd`).

One timeline entry per evaluated item — a pair (t, t+1) for moving objects and flow (timeline `pair`),
a time step for detection (timeline `frame`) — counted over the whole run, all in `ref` of the item's
first step (entity paths in rerun_paths):
- the observed occupancy: centres of the voxels holding frame t's depth points;
- the 3D flow, true and predicted, as arrows at the same voxels: the occupied voxels where either flow
  moves at least `min_flow` voxels, every k-th of them so that at most `max_arrows` remain, in metres
  per step, coloured by that length on one scale per entry (turbo: blue slow, red fast);
- the ground-truth boxes the evaluation scores against (green) and the model's boxes labelled with
  their scores (red);
- each view's camera (ref_T_cam, Pinhole, RGB) of frame t, for context;
- a text line naming the record and the steps.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from services.viz import rerun_paths as paths
from services.viz.rerun_archetypes import boxes3d, grid_box, pinhole, speed_colors, transform, voxel_centres_ref
from services.viz.rerun_blueprints import eval_blueprint

DEFAULT_MAX_ARROWS = 2000
DEFAULT_MIN_FLOW = 0.1  # voxels: below this a voxel's arrow would be a dot


def sample_flow_voxels(flows: list[np.ndarray], occupancy: np.ndarray | None, *, min_flow: float,
                       max_arrows: int) -> np.ndarray:
    """Voxels to draw flow arrows at: N×3 (z, y, x) indices, in C order, of the voxels that are occupied
    (Z×Y×X bool; every voxel when None) and where any of `flows` (each 3×Z×Y×X, voxels) has a norm of
    at least `min_flow`, thinned to every k-th so that N <= max_arrows."""
    moving = np.zeros(flows[0].shape[1:], bool)                      # Z×Y×X
    for flow in flows:
        moving |= np.linalg.norm(flow, axis=0) >= min_flow
    if occupancy is not None:
        moving &= occupancy
    zyx = np.argwhere(moving)                                        # N×3, C order
    stride = max(1, -(-len(zyx) // max_arrows))                      # ceil(N / max_arrows)
    return zyx[::stride]


class EvalRecorder:
    """Logs evaluation entries to a Rerun recording stream; one instance per evaluation run."""

    def __init__(self, *, recording, grid: Mapping, timeline: str, max_arrows: int = DEFAULT_MAX_ARROWS,
                 min_flow: float = DEFAULT_MIN_FLOW) -> None:
        from services.viz.rerun_sdk import require_rerun

        self.rr = require_rerun()
        self.rec = recording
        self.grid = dict(grid)
        self.voxel = (self.grid["xmax"] - self.grid["xmin"]) / self.grid["X"]
        self.timeline = timeline
        self.max_arrows = max_arrows
        self.min_flow = min_flow
        self.entries = 0
        self.rec.log(paths.REF, self.rr.ViewCoordinates.RDF, static=True)
        self.rec.log(paths.REF_GRID, grid_box(self.rr, self.grid), static=True)

    def log_entry(self, *, record: Mapping[str, np.ndarray], record_index: int, t0: int, t1: int | None = None,
                  occupancy: np.ndarray | None = None, flow_true: np.ndarray | None = None,
                  flow_pred: np.ndarray | None = None, boxes_true: np.ndarray | None = None,
                  boxes_pred: np.ndarray | None = None, scores_pred: np.ndarray | None = None,
                  note: str = "") -> int:
        """Log one entry (the next index on the timeline) and return its index.

        record: the evaluated record (for the cameras of step t0); occupancy: Z×Y×X bool in ref_t0;
        flow_true / flow_pred: 3×Z×Y×X, voxels, channels (x, y, z); boxes_true: G×7, boxes_pred: N×7
        with scores_pred N, all in ref_t0. What is None is not logged."""
        rr, rec = self.rr, self.rec
        index = self.entries
        if index == 0:  # the layout needs the number of views
            rec.send_blueprint(eval_blueprint(views=record["rgb"].shape[1]))
        rec.set_time(self.timeline, sequence=index)
        steps = f"t={t0}" if t1 is None else f"t={t0}→{t1}"
        rec.log(paths.EVAL_LOG, rr.TextLog(f"entry {index}: record {record_index}, {steps}" + (f", {note}" if note else "")))
        self._log_cameras(record, t0)
        if occupancy is not None:
            centres = voxel_centres_ref(np.argwhere(occupancy), self.grid)
            rec.log(paths.OCCUPANCY, rr.Points3D(centres, radii=0.3 * self.voxel, colors=[paths.OCCUPIED]))
        flows = [f for f in (flow_true, flow_pred) if f is not None]
        if flows:
            zyx = sample_flow_voxels(flows, occupancy, min_flow=self.min_flow, max_arrows=self.max_arrows)
            origins = voxel_centres_ref(zyx, self.grid)
            vectors = {path: flow[:, zyx[:, 0], zyx[:, 1], zyx[:, 2]].T * self.voxel      # N×3 metres per step
                       for path, flow in ((paths.FLOW_TRUE, flow_true), (paths.FLOW_PRED, flow_pred)) if flow is not None}
            vmax = max([float(np.linalg.norm(v, axis=1).max(initial=0.0)) for v in vectors.values()] + [1e-6])
            for path, vec in vectors.items():
                rec.log(path, rr.Arrows3D(origins=origins, vectors=vec.astype(np.float32),
                                          colors=speed_colors(np.linalg.norm(vec, axis=1), vmax),
                                          radii=0.05 * self.voxel))
        if boxes_true is not None:
            rec.log(paths.BOXES_TRUE, boxes3d(rr, boxes_true, colors=paths.TRUE_BOX))
        if boxes_pred is not None:
            scores = np.zeros(len(boxes_pred)) if scores_pred is None else np.asarray(scores_pred, np.float64)
            rec.log(paths.BOXES_PRED, boxes3d(rr, boxes_pred, colors=paths.PRED_BOX, labels=[f"{s:.2f}" for s in scores]))
        self.entries += 1
        return index

    def _log_cameras(self, record: Mapping[str, np.ndarray], t: int) -> None:
        rr = self.rr
        ref_T_world = np.linalg.inv(np.asarray(record["world_T_ref"][t], np.float64))
        _, V, H, W, _ = record["rgb"].shape
        for v in range(V):
            self.rec.log(paths.camera(v, paths.REF), transform(rr, ref_T_world @ record["world_T_cam"][t, v]))
            self.rec.log(paths.camera_image(v, paths.REF), pinhole(rr, record["pix_T_cam"][v], height=H, width=W))
            self.rec.log(paths.camera_image(v, paths.REF), rr.Image(record["rgb"][t, v], color_model="RGB"))


def open_eval_recorder(path, *, grid: Mapping, timeline: str, name: str) -> EvalRecorder:
    """An EvalRecorder writing to the .rrd `path` (checked with rerun_sdk.check_rrd_path first)."""
    from services.viz.rerun_sdk import open_recording

    return EvalRecorder(recording=open_recording(name=name, save_to=path), grid=grid, timeline=timeline)


def close_eval_recorder(recorder: EvalRecorder | None) -> None:
    if recorder is not None:
        from services.viz.rerun_sdk import close_recording

        close_recording(recorder.rec)
