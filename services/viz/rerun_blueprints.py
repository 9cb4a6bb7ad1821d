"""Default viewer layouts (Rerun blueprints) sent with each recording: a large 3D view of the recording's
root frame beside the camera images, the side panels folded away. The viewer's "reset blueprint"
restores them; a user's own layout takes precedence.
"""

from __future__ import annotations

from services.viz import rerun_paths as paths


def _rrb():
    from services.viz.rerun_sdk import require_rerun

    require_rerun()
    import rerun.blueprint as rrb

    return rrb


def _images(rrb, views: int, root: str):
    return [rrb.Spatial2DView(origin=paths.camera_image(v, root), name=f"cam{v}") for v in range(views)]


def record_blueprint(*, views: int):
    """`data preview --rerun`: the record in world, and each view's RGB-D."""
    rrb = _rrb()
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Spatial3DView(origin=paths.WORLD, name="world"),
                       rrb.Vertical(*_images(rrb, views, paths.WORLD)), column_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))


def eval_blueprint(*, views: int):
    """`eval ... --rerun`: occupancy, flow and boxes in ref, the cameras, and the entry log."""
    rrb = _rrb()
    return rrb.Blueprint(
        rrb.Horizontal(rrb.Spatial3DView(origin=paths.REF, name="ref"),
                       rrb.Vertical(*_images(rrb, views, paths.REF), rrb.TextLogView(origin=paths.EVAL_LOG, name="entries")),
                       column_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))


def stream_blueprint():
    """`stream view`: the world with the camera's trajectory and detections, the current frame, the latency."""
    rrb = _rrb()
    return rrb.Blueprint(
        # The eye rides behind and above the camera (StreamRecorder's chase entity), so the newest frame's
        # points and boxes stay in view as it drives.
        rrb.Horizontal(rrb.Spatial3DView(origin=paths.WORLD, name="world",
                                         eye_controls=rrb.EyeControls3D(tracking_entity=paths.STREAM_EYE)),
                       rrb.Vertical(rrb.Spatial2DView(origin=paths.STREAM_IMAGE, name="camera"),
                                    rrb.TimeSeriesView(origin=paths.LATENCY, name="end-to-end latency (ms)"),
                                    row_shares=[2, 1]),
                       column_shares=[3, 2]),
        rrb.BlueprintPanel(state="collapsed"), rrb.SelectionPanel(state="collapsed"))
