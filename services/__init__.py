"""n3dmap services: everything that talks to the outside (CLI, Ray jobs, inference, streaming)."""
