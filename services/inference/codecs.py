"""Wire encodings of arrays and images: raw little-endian tensors, PNG, `.npy` and `.npz`.

Decoding is defensive: every failure raises InvalidInput naming the field, sizes are checked before
anything is allocated, nothing is ever unpickled (`allow_pickle=False`), and PNG decoding is capped
against decompression bombs.
"""

from __future__ import annotations

import base64
import binascii
import io
import math
import zipfile
import zlib

import numpy as np
from PIL import Image as PILImage

from n3dmap.v1 import types_pb2
from services.inference.errors import InvalidInput

# dtypes accepted on the wire (numpy names); everything is little-endian on the wire.
WIRE_DTYPES = ("uint8", "uint16", "int32", "int64", "float32", "float64", "bool")
MAX_ARRAY_BYTES = 256 * 2**20
MAX_IMAGE_PIXELS = 16 * 2**20
# The pixels one request may decode over all its images, rgb and depth each counted (a pair of 16-view instants
# at 1024×1024 is 2 × 16 × 2 × 2**20). The per-image cap alone let a request of 64 compressed PNGs within the
# 64 MiB body cap (a flat 4096×4096 image compresses to kilobytes) decode to ~1 G pixels, GBs before the model.
MAX_REQUEST_PIXELS = 64 * 2**20


class PixelBudget:
    """What is left of one request's MAX_REQUEST_PIXELS; each image is charged from its header or declared shape,
    before it is decoded, so a request over budget is refused before the memory is spent."""

    def __init__(self, limit: int = MAX_REQUEST_PIXELS):
        self.limit, self.left = limit, limit

    def take(self, pixels: int, field: str) -> None:
        if pixels > self.left:
            raise InvalidInput(field, f"an image of {pixels} pixels takes the request past its budget of "
                                      f"{self.limit} pixels over all its images ({self.limit - self.left} used)")
        self.left -= pixels


def image_pixels(shape) -> int:
    """Pixels of an image array of `shape` (H×W or H×W×C; any other shape: its element count, refused later)."""
    shape = tuple(int(s) for s in shape)
    return shape[0] * shape[1] if len(shape) in (2, 3) else math.prod(shape)


def array_from_bytes(data: bytes, dtype: str, shape, field: str) -> np.ndarray:
    """Raw little-endian C-order bytes -> array, checking dtype name, shape and byte count."""
    if dtype not in WIRE_DTYPES:
        raise InvalidInput(field, f"dtype {dtype!r} is not one of {', '.join(WIRE_DTYPES)}")
    shape = tuple(int(s) for s in shape)
    if any(s < 0 for s in shape) or len(shape) > 8:
        raise InvalidInput(field, f"bad shape {list(shape)}")
    dt = np.dtype(dtype).newbyteorder("<")
    want = math.prod(shape) * dt.itemsize
    if want > MAX_ARRAY_BYTES:
        raise InvalidInput(field, f"array of {want} bytes exceeds the {MAX_ARRAY_BYTES}-byte cap")
    if len(data) != want:
        raise InvalidInput(field, f"{len(data)} bytes do not match dtype {dtype} × shape {list(shape)} "
                                  f"({want} bytes)")
    return np.frombuffer(data, dtype=dt).reshape(shape).astype(dt.newbyteorder("="), copy=False)


def array_to_bytes(arr: np.ndarray) -> tuple[str, list[int], bytes]:
    """Array -> (dtype name, shape, little-endian C-order bytes)."""
    arr = np.asarray(arr)
    name = arr.dtype.name
    if name not in WIRE_DTYPES:
        raise ValueError(f"dtype {name} cannot travel on the wire; use one of {WIRE_DTYPES}")
    le = np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("<"))
    return name, list(arr.shape), le.tobytes()


def tensor_to_numpy(msg: types_pb2.Tensor, field: str) -> np.ndarray:
    return array_from_bytes(msg.data, msg.dtype, msg.shape, field)


def numpy_to_tensor(arr: np.ndarray) -> types_pb2.Tensor:
    dtype, shape, data = array_to_bytes(arr)
    return types_pb2.Tensor(dtype=dtype, shape=shape, data=data)


def b64decode(text: str, field: str) -> bytes:
    try:
        return base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError) as e:
        raise InvalidInput(field, f"not valid base64 ({e})") from None


def b64encode(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def _open_png(data: bytes, field: str, budget: PixelBudget | None) -> PILImage.Image:
    try:
        img = PILImage.open(io.BytesIO(data), formats=["PNG"])   # reads the header only
        if img.width * img.height > MAX_IMAGE_PIXELS:
            raise InvalidInput(field, f"image of {img.width}×{img.height} pixels exceeds the cap")
        if budget is not None:
            budget.take(img.width * img.height, field)
        img.load()
        return img
    except InvalidInput:
        raise
    except (OSError, ValueError, SyntaxError, PILImage.DecompressionBombError) as e:
        raise InvalidInput(field, f"undecodable PNG ({type(e).__name__}: {e})") from None


def decode_png_rgb(data: bytes, field: str, budget: PixelBudget | None = None) -> np.ndarray:
    """PNG (RGB, RGBA, grey or palette) -> H×W×3 uint8, charged to `budget` before it is decoded."""
    img = _open_png(data, field, budget)
    if img.mode not in ("RGB", "RGBA", "L", "P", "LA"):
        raise InvalidInput(field, f"RGB PNG must be 8-bit colour or grey, got mode {img.mode}")
    return np.asarray(img.convert("RGB"), dtype=np.uint8)


def decode_png_depth(data: bytes, field: str, budget: PixelBudget | None = None) -> np.ndarray:
    """16-bit grey PNG of millimetres -> H×W float32 metres (0 stays 0 = missing), charged to `budget` first."""
    img = _open_png(data, field, budget)
    if img.mode not in ("I;16", "I;16B", "I;16L", "I"):
        raise InvalidInput(field, f"depth PNG must be 16-bit greyscale millimetres, got mode {img.mode}")
    mm = np.asarray(img).astype(np.float32)
    if mm.ndim != 2:
        raise InvalidInput(field, f"depth PNG must have one channel, got shape {mm.shape}")
    return mm / 1000.0


def encode_png_rgb(rgb: np.ndarray) -> bytes:
    """H×W×3 uint8 -> PNG bytes."""
    buf = io.BytesIO()
    PILImage.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8), mode="RGB").save(buf, format="PNG")
    return buf.getvalue()


def encode_png_depth(depth_m: np.ndarray) -> bytes:
    """H×W metres -> 16-bit PNG of millimetres (rounded, clipped to 65.535 m)."""
    mm = np.clip(np.round(np.asarray(depth_m, dtype=np.float64) * 1000.0), 0, 65535).astype(np.uint16)
    buf = io.BytesIO()
    PILImage.fromarray(mm).save(buf, format="PNG")
    return buf.getvalue()


def load_npy(data: bytes, field: str) -> np.ndarray:
    _check_npy_size(data, field)
    try:
        arr = np.load(io.BytesIO(data), allow_pickle=False)
    except (ValueError, OSError, EOFError) as e:
        raise InvalidInput(field, f"not a .npy array without pickles ({e})") from None
    if not isinstance(arr, np.ndarray):
        raise InvalidInput(field, "expected one .npy array")
    return arr


def _check_npy_size(data: bytes, field: str) -> None:
    """InvalidInput unless the .npy header's shape and dtype fit in the bytes that follow it. Why: np.load
    allocates the declared array before reading it, so a 100-byte member declaring shape (2**40,) asked for a
    TiB (MemoryError: a 500) — the inflation cap counts the member's bytes, not what its header claims."""
    stream = io.BytesIO(data)
    try:
        version = np.lib.format.read_magic(stream)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        shape, _, dtype = read_header(stream)
    except (ValueError, OSError, EOFError, TypeError) as e:
        raise InvalidInput(field, f"not a .npy array without pickles ({e})") from None
    if dtype.hasobject:
        return   # np.load refuses it below (allow_pickle=False), naming why
    declared = int(np.prod(shape, dtype=object)) * dtype.itemsize
    if declared > len(data) - stream.tell():
        raise InvalidInput(field, f".npy header declares {list(shape)} {dtype} ({declared} bytes) but "
                                  f"{len(data) - stream.tell()} bytes follow it")


def load_npz(data: bytes, field: str = "body", max_bytes: int = MAX_ARRAY_BYTES) -> dict[str, np.ndarray]:
    """`.npz` bytes -> {name: array}, refusing pickles and members that inflate past `max_bytes`."""
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            total = sum(info.file_size for info in zf.infolist())
            if total > max_bytes:
                raise InvalidInput(field, f".npz inflates to {total} bytes, over the {max_bytes}-byte cap")
            out = {}
            for info in zf.infolist():
                name = info.filename[:-4] if info.filename.endswith(".npy") else info.filename
                out[name] = load_npy(zf.read(info), f"{field}[{name}]")
            return out
    except InvalidInput:
        raise
    except (zipfile.BadZipFile, zlib.error, ValueError, OSError, EOFError, NotImplementedError) as e:
        # zlib.error: a member whose deflate stream is corrupt (it is not an OSError)
        raise InvalidInput(field, f"not a readable .npz archive ({e})") from None


def save_npz(arrays: dict[str, np.ndarray]) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()
