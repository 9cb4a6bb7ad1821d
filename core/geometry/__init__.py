"""Pure geometry: frames, poses, cameras, the voxel grid, resampling, free space and boxes.

See docs/conventions.md for the conventions every module here states at its top.
"""
