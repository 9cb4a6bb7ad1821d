"""One record as the bytes of a shard member: an uncompressed npz of the record's arrays, never pickled."""

from __future__ import annotations

import io
import zipfile
from typing import Mapping

import numpy as np

from core.data.record import RECORD_KEYS, validate_record
from core.data.shards.layout import one_line
from core.errors import DataError


def encode_record(rec: Mapping[str, np.ndarray]) -> bytes:
    """The npz bytes of one record (np.savez, uncompressed; keys in schema order)."""
    buf = io.BytesIO()
    np.savez(buf, **{k: np.ascontiguousarray(rec[k]) for k in RECORD_KEYS})
    return buf.getvalue()


def decode_record(npz_bytes: bytes, where: str) -> dict[str, np.ndarray]:
    """Decode one `<key>.npz` member into a validated record (never unpickles anything).

    Raises DataError("<where>: ...") if the bytes are not an npz archive, fail their CRC, hold pickled
    objects, or do not satisfy the record schema (core.data.record.validate_record).
    """
    try:
        loaded = np.load(io.BytesIO(npz_bytes), allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise DataError(f"{where}: not an npz archive (a single .npy array)")
        with loaded:
            rec = {name: loaded[name] for name in loaded.files}
    except DataError:
        raise
    except (ValueError, OSError, EOFError, KeyError, zipfile.BadZipFile) as e:
        raise DataError(f"{where}: cannot decode npz: {one_line(e)}") from None
    validate_record(rec, where)
    return rec
