"""Flushing to disk what a rename is about to make official (stage markers, training checkpoints, a stage's
selected bundle).

Why: a rename is atomic for readers, but after a power loss the new name can survive over file contents that
never reached the disk — an empty stage marker that says "finished", or the newest checkpoint over empty files
while the older ones were already deleted. Flushing the files before the rename, and the folder after it, closes
that window.
"""

from __future__ import annotations

import os
from pathlib import Path


def fsync_path(path: str | os.PathLike) -> None:
    """Flush a file's or a folder's contents (a folder: its entries, i.e. renames into it) to disk."""
    fd = os.open(Path(path), os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_tree(folder: str | os.PathLike) -> None:
    """Flush every file directly in `folder` (checkpoints and bundles are flat), then the folder itself."""
    folder = Path(folder)
    for path in folder.iterdir():
        if path.is_file():
            fsync_path(path)
    fsync_path(folder)
