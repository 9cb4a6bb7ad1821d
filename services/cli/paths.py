"""Output paths the user gave, checked before any slow work: a folder a command will create (or write into)
must be creatable — no regular file on the way, a writable folder above it.

Why: otherwise the mistake shows only when the result is written, after the work (an evaluation, a dataset's
rendering), as a bare `[Errno 20] Not a directory: '...'` that names neither the option nor which part of
the path is wrong. Nothing is created here, so a refused command leaves no empty folder behind.
"""

from __future__ import annotations

import os
from pathlib import Path

from core.errors import ConfigError


def check_creatable_dir(path: str | os.PathLike, flag: str) -> None:
    """ConfigError naming `flag` unless `path` is a folder, or could be created as one, and written into."""
    given = Path(path)
    target = given.absolute()
    existing = target
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        where = "is a file" if existing == target else f"cannot be created: {existing} is a file, not a folder"
        raise ConfigError(f"{flag} {given} {where}")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ConfigError(f"{flag} {given}: {existing} is not writable")
