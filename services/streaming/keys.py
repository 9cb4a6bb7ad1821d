"""Key expressions of the n3dmap zenoh streams (docs/architecture.md#streaming-over-zenoh)."""

from __future__ import annotations

PREFIX = "n3dmap"


def rgbd(camera: str) -> str:
    """Frames in: `n3dmap/<camera>/rgbd`."""
    return f"{PREFIX}/{camera}/rgbd"


def moving_objects(camera: str) -> str:
    """Detections out: `n3dmap/<camera>/moving_objects`."""
    return f"{PREFIX}/{camera}/moving_objects"


def egomotion(camera: str) -> str:
    """Egomotion out: `n3dmap/<camera>/egomotion`."""
    return f"{PREFIX}/{camera}/egomotion"


def bridge_token(bridge_id: str) -> str:
    """Liveliness token of a running bridge."""
    return f"{PREFIX}/@bridge/{bridge_id}"


def bridge_status(bridge_id: str) -> str:
    """Queryable answering the bridge's JSON status."""
    return f"{PREFIX}/@bridge/{bridge_id}/status"


def camera_from_key(key: str) -> str | None:
    """`n3dmap/<camera>/<stream>` → `<camera>`; None if the key is not of that form."""
    parts = key.split("/")
    if len(parts) != 3 or parts[0] != PREFIX or not parts[1] or parts[1].startswith("@"):
        return None
    return parts[1]
