"""n3dmap core: the pure library (geometry, data, models, losses, task steps, evaluation).

Imports torch / numpy / scipy only — never ray, fastapi, grpc or zenoh (DESIGN.md §1).
"""

__version__ = "0.1.0"
