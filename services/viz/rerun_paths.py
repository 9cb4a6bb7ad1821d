"""Where n3dmap puts things in a Rerun recording: entity paths, timelines, colours (README "3D viewer
(Rerun)"). One place, so the three recorders (dataset, evaluation, live stream), the README and the
tests that read recordings back agree.

Frames (docs/conventions.md#frames): every 3D root is an OpenCV-style frame — X right, Y down, Z forward, metres —
logged as `ViewCoordinates.RDF`, so the viewer shows −Y as up. Datasets and the live stream are drawn
in `world` (camera poses `world_T_cam`, the map frame `world_T_ref`); evaluations in `ref`, the map's
frame at the pair's first step (boxes, flow and voxels there, cameras as `ref_T_cam`). A Transform3D
logged at an entity is its `parent_T_entity` pose (Rerun's default relation, parent-from-child).
Boxes (x, y, z, lx, ly, lz, yaw) become centres, half sizes (lx/2, ly/2, lz/2) and the quaternion of the
rotation `yaw` about the frame's Y axis. Flow (voxels per step, channels x, y, z) becomes arrows in
metres per step: the vector × voxel size. Velocities (m/s) become arrows of the distance in one second.
"""

from __future__ import annotations

# -- timelines (all sequences)
STEP = "step"      # data preview: the record's time step t = 0..T-1
PAIR = "pair"      # eval moving|flow: the evaluated pair (t, t+1), counted over the whole run
FRAME = "frame"    # eval detection: the evaluated (record, t); stream view: the camera's frame sequence
SOURCE_TIME = "source_time"  # stream view: the frame's source timestamp, when it was sent (a timestamp timeline)

# -- dataset preview (n3dmap data preview --rerun), frame `world`
WORLD = "world"
WORLD_REF = "world/ref"                   # Transform3D world_T_ref(t)
WORLD_GRID = "world/ref/grid"             # Boxes3D: the map grid's bounds, in ref
BOXES = "world/boxes"                     # Boxes3D: ground-truth boxes valid at t (moving ones red)
BOX_MOTION = "world/boxes/motion"         # Arrows3D: centre(t) -> centre(t+1) of moving boxes


def camera(view: int, root: str = WORLD) -> str:
    """Transform3D root_T_cam of camera `view`."""
    return f"{root}/cam{view}"


def camera_image(view: int, root: str = WORLD) -> str:
    """Pinhole + Image (rgb) + DepthImage of camera `view` (a child of its pose)."""
    return f"{camera(view, root)}/image"


def camera_points(view: int, root: str = WORLD) -> str:
    """Points3D: the depth of camera `view` back-projected, in the camera frame (`--points`)."""
    return f"{camera(view, root)}/points"


# -- evaluations (n3dmap eval moving|flow|detection --rerun), frame `ref`
REF = "ref"
REF_GRID = "ref/grid"                     # Boxes3D: the map grid's bounds (static)
OCCUPANCY = "ref/occupancy"               # Points3D: centres of the occupied voxels (observed depth)
FLOW_TRUE = "ref/flow/true"               # Arrows3D: ground-truth flow at the sampled voxels
FLOW_PRED = "ref/flow/pred"               # Arrows3D: the model's flow at the same voxels
BOXES_TRUE = "ref/boxes/true"             # Boxes3D: ground-truth boxes the evaluation scores against
BOXES_PRED = "ref/boxes/pred"             # Boxes3D: the model's boxes, labelled with their scores
EVAL_LOG = "eval/log"                     # TextLog: which record and steps each entry is

# -- live stream (n3dmap stream view), frame `world`
STREAM_CAMERA = "world/camera"            # Transform3D world_T_cam of the newest frame
STREAM_IMAGE = "world/camera/image"       # Pinhole + Image + DepthImage of the newest frame
STREAM_EYE = "world/camera/chase"         # static Transform3D + Pinhole behind and above the camera: the 3D
                                          # view's default eye follows it (a chase view of the scene)
TRAJECTORY = "world/trajectory"           # LineStrips3D: camera centres from the frames' poses
TRAJECTORY_EGO = "world/trajectory_egomotion"  # LineStrips3D: the bridge's egomotion chained from frame 1
DETECTIONS_FRAME = "world/detections"     # Transform3D world_T_frame of the newest detections (their `ref`)
DETECTIONS = "world/detections/moving_objects"  # Boxes3D: one entry per Detections message
VELOCITIES = "world/detections/velocities"      # Arrows3D: each box's velocity (m/s, drawn over 1 s)
LATENCY = "stats/end_to_end_ms"          # Scalars: source timestamp -> detections received

# -- colours (RGB)
STATIC_BOX = (40, 180, 60)
MOVING_BOX = (230, 40, 40)
TRUE_BOX = (40, 180, 60)
PRED_BOX = (230, 40, 40)
GRID_BOX = (150, 150, 150)
OCCUPIED = (160, 160, 170)
TRAJECTORY_COLOR = (60, 120, 230)
TRAJECTORY_EGO_COLOR = (240, 160, 30)
