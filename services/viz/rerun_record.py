"""One dataset record as a Rerun recording (`n3dmap data preview DIR --rerun FILE.rrd`).

Everything is drawn in `world` on the `step` timeline (t = 0..T-1; entity paths in rerun_paths):
each view's camera as its pose world_T_cam(t) with a Pinhole, its RGB image and its depth — a
DepthImage that the viewer back-projects, or with `points=True` the back-projected points themselves
(useful for sparse, LiDAR-like depth) — the map frame world_T_ref(t) holding the grid's bounds, and
the ground-truth boxes valid at t (moving ones red, static green, labelled with their track ids) with
arrows from each moving box's centre at t to its centre at t+1.
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from services.viz import rerun_paths as paths
from services.viz.rerun_archetypes import boxes3d, depth_points, grid_box, pinhole, transform
from services.viz.rerun_blueprints import record_blueprint


def log_record(rec, record: Mapping[str, np.ndarray], *, grid: Mapping | None = None, points: bool = False) -> None:
    """Log `record` (docs/data.md#records: rgb T×V×H×W×3, depth T×V×H×W, pix_T_cam V×4×4, world_T_cam
    T×V×4×4, world_T_ref T×4×4, boxes T×K×7 in world, box_valid T×K, box_id K, box_moving K) to the
    recording stream `rec`; `grid` is the manifest's grid dict (drawn when given)."""
    from services.viz.rerun_sdk import require_rerun

    rr = require_rerun()
    T, V, H, W, _ = record["rgb"].shape
    rec.send_blueprint(record_blueprint(views=V))
    rec.log(paths.WORLD, rr.ViewCoordinates.RDF, static=True)
    if grid is not None:
        rec.log(paths.WORLD_GRID, grid_box(rr, grid), static=True)
    for v in range(V):  # intrinsics are per view, constant over the record
        rec.log(paths.camera_image(v), pinhole(rr, record["pix_T_cam"][v], height=H, width=W), static=True)

    boxes, valid = record["boxes"], record["box_valid"].astype(bool)        # T×K×7, T×K
    ids, moving = record["box_id"], record["box_moving"].astype(bool)       # K, K
    for t in range(T):
        rec.set_time(paths.STEP, sequence=t)
        rec.log(paths.WORLD_REF, transform(rr, record["world_T_ref"][t]))
        for v in range(V):
            rec.log(paths.camera(v), transform(rr, record["world_T_cam"][t, v]))
            rec.log(paths.camera_image(v), rr.Image(record["rgb"][t, v], color_model="RGB"))
            if points:
                rec.log(paths.camera_points(v), rr.Points3D(depth_points(record["depth"][t, v], record["pix_T_cam"][v]),
                                                            radii=-1.5))  # negative: screen-space pixels
            else:
                rec.log(paths.camera_image(v), rr.DepthImage(record["depth"][t, v], meter=1.0))
        k = np.flatnonzero(valid[t])
        rec.log(paths.BOXES, boxes3d(rr, boxes[t, k], colors=np.where(moving[k, None], paths.MOVING_BOX, paths.STATIC_BOX),
                                     labels=[f"id {int(ids[j])}" + (" moving" if moving[j] else "") for j in k]))
        # Motion t -> t+1 of the moving boxes valid at both steps; the last step has none (an empty
        # entry, so the arrows of T-2 do not linger at T-1).
        m = np.flatnonzero(valid[t] & moving & (valid[t + 1] if t + 1 < T else False))
        start = boxes[t, m, :3]
        end = boxes[t + 1, m, :3] if t + 1 < T else start
        rec.log(paths.BOX_MOTION, rr.Arrows3D(origins=start, vectors=end - start, colors=[paths.MOVING_BOX],
                                              labels=[f"id {int(ids[j])}" for j in m]))
