"""n3dmap core: the pure library (geometry, data, models, losses, task steps, evaluation).

Imports torch, numpy, scipy and safetensors (Pillow and OpenCV where image files and the 2D flow
baseline need them) — never ray, fastapi, grpc or zenoh (docs/architecture.md#packages-and-the-import-rule).
"""

__version__ = "0.1.0"
