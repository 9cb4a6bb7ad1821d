"""Inference over a loaded Bundle, shared by every transport (REST, gRPC, zenoh). See docs/architecture.md.

Each function takes batched tensors on the bundle's device and returns a dict of tensors.
"""

from core.pipeline.detect import detect
from core.pipeline.egomotion import estimate_egomotion
from core.pipeline.encoding import FrameEncoding, encode_previous
from core.pipeline.flow import estimate_flow, flow_step
from core.pipeline.map import map_frames
from core.pipeline.moving import moving_objects, moving_step

__all__ = ["detect", "estimate_egomotion", "estimate_flow", "flow_step", "map_frames", "moving_objects",
           "FrameEncoding", "encode_previous", "moving_step"]
