"""Pure geometry: frames, poses, cameras, the voxel grid, resampling, free space and boxes.

See DESIGN.md §2 for the conventions every module here states at its top.
"""
