"""Wire codecs against obvious references (struct packing, PIL), and their refusals."""

import io
import struct
import zipfile

import numpy as np
import pytest

from services.inference import codecs
from services.inference.errors import InvalidInput


def _reference_le_bytes(arr: np.ndarray) -> bytes:
    fmt = {"float32": "f", "float64": "d", "uint16": "H", "int32": "i", "uint8": "B"}[arr.dtype.name]
    return struct.pack("<" + fmt * arr.size, *arr.ravel().tolist())


@pytest.mark.parametrize("dtype", ["float32", "float64", "uint16", "int32", "uint8"])
def test_array_bytes_are_little_endian_c_order_and_round_trip(dtype):
    arr = (np.arange(24).reshape(2, 3, 4) * 7 % 11).astype(dtype)
    name, shape, data = codecs.array_to_bytes(arr)
    assert (name, shape, data) == (dtype, [2, 3, 4], _reference_le_bytes(arr))
    back = codecs.array_from_bytes(data, name, shape, "x")
    assert back.dtype == arr.dtype and np.array_equal(back, arr)
    big_endian = arr.astype(arr.dtype.newbyteorder(">"))
    assert codecs.array_to_bytes(big_endian)[2] == data


def test_tensor_proto_round_trip():
    arr = np.random.default_rng(0).standard_normal((3, 4, 4)).astype(np.float32)
    assert np.array_equal(codecs.tensor_to_numpy(codecs.numpy_to_tensor(arr), "t"), arr)


@pytest.mark.parametrize("dtype,shape,nbytes,needle", [
    ("float16", [2], 4, "dtype"), ("object", [1], 8, "dtype"), ("float32", [2, 2], 12, "bytes"),
    ("float32", [-1], 4, "shape"), ("uint8", [2**20, 2**20], 0, "cap")])
def test_array_from_bytes_refuses_bad_descriptions(dtype, shape, nbytes, needle):
    with pytest.raises(InvalidInput) as e:
        codecs.array_from_bytes(b"\0" * nbytes, dtype, shape, "views[0].depth.array")
    assert e.value.field == "views[0].depth.array" and needle in str(e.value)


def test_png_rgb_and_depth_round_trip():
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    assert np.array_equal(codecs.decode_png_rgb(codecs.encode_png_rgb(rgb), "rgb"), rgb)
    depth = rng.uniform(0, 60, (5, 7)).astype(np.float32)
    depth[0, 0] = 0
    back = codecs.decode_png_depth(codecs.encode_png_depth(depth), "depth")
    assert back.dtype == np.float32 and np.abs(back - depth).max() <= 0.0005 + 1e-6 and back[0, 0] == 0


def test_png_refusals_name_the_field():
    with pytest.raises(InvalidInput, match="undecodable PNG") as e:
        codecs.decode_png_rgb(b"\x89PNG\r\n\x1a\nnot really", "views[2].rgb.png")
    assert e.value.field == "views[2].rgb.png"
    eight_bit = codecs.encode_png_rgb(np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(InvalidInput, match="16-bit"):
        codecs.decode_png_depth(eight_bit, "views[0].depth.png")


def test_npz_is_read_without_pickles_and_with_a_size_cap():
    arrays = {"rgb": np.zeros((1, 2, 2, 3), np.uint8), "depth": np.ones((1, 2, 2), np.float32)}
    back = codecs.load_npz(codecs.save_npz(arrays))
    assert set(back) == {"rgb", "depth"} and all(np.array_equal(back[k], arrays[k]) for k in arrays)
    buf = io.BytesIO()
    np.savez(buf, bad=np.array([{"a": 1}], dtype=object))
    with pytest.raises(InvalidInput, match="pickle"):
        codecs.load_npz(buf.getvalue())
    bomb = io.BytesIO()
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("x.npy", b"\0" * (3 * 2**20))
    with pytest.raises(InvalidInput, match="cap"):
        codecs.load_npz(bomb.getvalue(), max_bytes=2**20)
    with pytest.raises(InvalidInput, match="npz"):
        codecs.load_npz(b"definitely not a zip")


def _npy_header(shape: tuple, dtype: str = "<f4") -> bytes:
    """A .npy version 1.0 file's magic and header, written by hand (the format's spec), without its data."""
    header = repr({"descr": dtype, "fortran_order": False, "shape": shape}).encode()
    header += b" " * (-(10 + len(header) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header


def test_a_header_declaring_more_than_its_bytes_is_refused_before_any_allocation():
    # np.load would allocate the declared TiB first (a MemoryError, i.e. a 500)
    body = io.BytesIO()
    with zipfile.ZipFile(body, "w") as zf:
        zf.writestr("rgb.npy", _npy_header((2**40,)) + b"\0" * 16)
    with pytest.raises(InvalidInput, match=r"declares \[1099511627776\] float32 .* but 16 bytes follow") as e:
        codecs.load_npz(body.getvalue())
    assert e.value.field == "body[rgb]"
    exact = _npy_header((4,)) + np.arange(4, dtype="<f4").tobytes()   # the hand-written header reads as numpy's
    assert np.array_equal(codecs.load_npy(exact, "x"), np.arange(4, dtype=np.float32))


def test_a_corrupt_deflate_member_is_a_4xx_not_a_zlib_error():
    body = io.BytesIO()
    with zipfile.ZipFile(body, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("rgb.npy", codecs.save_npz({"a": np.zeros(1000, np.float32)}))   # compressible content
    data = bytearray(body.getvalue())
    start = data.index(b"rgb.npy") + len("rgb.npy")     # the member's compressed bytes follow its local header name
    data[start + 10:start + 40] = b"\xff" * 30
    with pytest.raises(InvalidInput, match="not a readable .npz archive"):
        codecs.load_npz(bytes(data))
