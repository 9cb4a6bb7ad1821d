"""The shard format's names and rules (docs/data.md#shards-and-manifest): what a dataset directory's files are
called, what a record key may be, how many bytes a tar member takes."""

from __future__ import annotations

import re

FORMAT_NAME = "n3dmap-shards"
SCHEMA_VERSION = 1
MANIFEST_NAME = "manifest.json"
DEFAULT_SHARD_BYTES = 256 << 20
KEY_FIELD = "__key__"

RECORD_KEY_RE = re.compile(r"^[A-Za-z0-9_-]+$")
SHARD_NAME_RE = re.compile(r"^shard-\d{5,}\.tar$")
PARTIAL_SUFFIX = ".partial"
TAR_BLOCK = 512


def shard_filename(index: int) -> str:
    """Filename of shard `index`: shard-00000.tar, shard-00001.tar, ..."""
    return f"shard-{index:05d}.tar"


def one_line(e: BaseException) -> str:
    """An exception's message on one line (its type when it has none), for DataError messages."""
    text = str(e) or type(e).__name__
    return " ".join(text.split())


def member_bytes(payload_size: int) -> int:
    """Bytes a member takes in a tar: one header block plus the payload padded to whole blocks."""
    return TAR_BLOCK + -(-payload_size // TAR_BLOCK) * TAR_BLOCK
