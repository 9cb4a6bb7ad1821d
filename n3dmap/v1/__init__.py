"""n3dmap.v1 messages (types_pb2: Tensor, Image, Frame, Box3D, Detections) and the Inference service."""
