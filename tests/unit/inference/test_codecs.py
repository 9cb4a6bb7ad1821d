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
