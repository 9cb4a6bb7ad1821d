"""Shards: round trips (sequential and by index, across several shards) and every corruption named."""

from __future__ import annotations

import hashlib
import io
import json
import tarfile

import numpy as np
import pytest

from core.data.shards import (MANIFEST_NAME, ShardDataset, dataset_shard_paths, decode_record, encode_record,
                              iter_shard, iter_tar_members, load_manifest, write_dataset)
from core.errors import DataError

GRID = {"xmin": -16.0, "xmax": 16.0, "ymin": -4.0, "ymax": 4.0, "zmin": -16.0, "zmax": 16.0,
        "Z": 32, "Y": 8, "X": 32}


def _write(out, records, **kw):
    kw.setdefault("shard_bytes", 9000)
    return write_dataset(out, records, split="train", preset_name="tiny", grid=GRID,
                         generator={"source": "test"}, seed=7, **kw)


def _assert_same(a: dict, b: dict):
    assert set(a) == set(b)
    for k in a:
        assert a[k].dtype == b[k].dtype and a[k].shape == b[k].shape, k
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


@pytest.fixture
def records(make_record):
    # Records of ~3.5 kB (4 kB as tar members) with a 9 kB shard limit: two per shard, varying K.
    return [make_record(K=i % 3, seed=i) for i in range(7)]


def _naive_shard_contents(path) -> dict[str, bytes]:
    """Slow obvious reader: every member of the tar, by name (reference for the writer)."""
    with tarfile.open(path) as tar:
        return {m.name: tar.extractfile(m).read() for m in tar.getmembers()}


def test_round_trip_sequential_and_by_index(tmp_path, records):
    calls = []
    manifest = _write(tmp_path / "ds", records, on_record=lambda n, key: calls.append((n, key)))
    assert calls == [(i + 1, f"ep{i:06d}") for i in range(7)]
    assert manifest["num_records"] == 7 and len(manifest["shards"]) == 4
    assert [s["num_records"] for s in manifest["shards"]] == [2, 2, 2, 1]
    assert manifest["dims"]["K"] == [0, 2] and manifest["dims"]["T"] == [2, 2]
    assert (manifest["preset"], manifest["split"], manifest["seed"], manifest["grid"]) == ("tiny", "train", 7, GRID)

    # The manifest agrees with the files on disk (sha256 and size), checked the obvious way.
    for entry in manifest["shards"]:
        data = (tmp_path / "ds" / entry["filename"]).read_bytes()
        assert hashlib.sha256(data).hexdigest() == entry["sha256"] and len(data) == entry["bytes"]
        members = _naive_shard_contents(tmp_path / "ds" / entry["filename"])
        assert list(members) == [f"{k}.npz" for k in entry["keys"]]
    assert load_manifest(tmp_path / "ds") == json.loads((tmp_path / "ds" / MANIFEST_NAME).read_text())

    ds = ShardDataset(tmp_path / "ds", verify=True)
    assert len(ds) == 7
    for got, want in zip(ds, records, strict=True):
        _assert_same(got, want)
    for i in [6, 0, 3, 5, 1, -1]:           # random order, crossing shards
        _assert_same(ds[i], records[i])
        assert ds.key(i) == f"ep{i % 7:06d}"
    with pytest.raises(IndexError):
        ds[7]
    assert ds.verify() == {"shards": 4, "records": 7, "bytes": sum(s["bytes"] for s in manifest["shards"])}


def test_iter_shard_from_path_and_bytes(tmp_path, records):
    manifest = _write(tmp_path / "ds", records)
    entry = manifest["shards"][1]
    path = tmp_path / "ds" / entry["filename"]
    from_path = list(iter_shard(path, expected_keys=entry["keys"]))
    from_bytes = list(iter_shard(path.read_bytes(), name=entry["filename"]))
    assert [k for k, _ in from_path] == [k for k, _ in from_bytes] == ["ep000002", "ep000003"]
    for (_, a), (_, b), want in zip(from_path, from_bytes, records[2:4]):
        _assert_same(a, want)
        _assert_same(b, want)


def test_tar_members_are_the_undecoded_records_checked_against_the_manifest(tmp_path, records):
    """What a Ray read task yields: (key, npz bytes), the bytes decode_record turns into the record."""
    manifest = _write(tmp_path / "ds", records)
    paths, keys, _ = dataset_shard_paths(tmp_path / "ds")
    entry = manifest["shards"][1]
    assert keys[entry["filename"]] == entry["keys"] and len(paths) == len(manifest["shards"])
    with open(tmp_path / "ds" / entry["filename"], "rb") as f:
        members = list(iter_tar_members(f, entry["filename"], entry["keys"]))
    assert [k for k, _ in members] == ["ep000002", "ep000003"]
    for (key, payload), want in zip(members, records[2:4]):
        _assert_same(decode_record(payload, key), want)
    with open(tmp_path / "ds" / entry["filename"], "rb") as f:
        msg = _one_line_error(lambda: list(iter_tar_members(f, entry["filename"], ["ep000002"])))
    assert "shard-00001.tar" in msg and "not in the manifest" in msg
    # a shard cut short is refused before any read task starts, naming it, as ShardDataset refuses it
    shard = tmp_path / "ds" / entry["filename"]
    shard.write_bytes(shard.read_bytes()[:-512])
    msg = _one_line_error(lambda: dataset_shard_paths(tmp_path / "ds"))
    assert entry["filename"] in msg and "differs from the manifest" in msg


def test_deterministic_bytes_and_custom_keys(tmp_path, records):
    keyed = [dict(r, __key__=f"frame-{i:03d}") for i, r in enumerate(records)]
    a = _write(tmp_path / "a", keyed)
    b = _write(tmp_path / "b", keyed)
    assert [s["sha256"] for s in a["shards"]] == [s["sha256"] for s in b["shards"]]
    assert ShardDataset(tmp_path / "a").key(4) == "frame-004"


def test_single_big_record_gets_its_own_shard(tmp_path, make_record):
    recs = [make_record(H=64, W=64), make_record(seed=1)]
    manifest = _write(tmp_path / "ds", recs, shard_bytes=1000)
    assert [s["num_records"] for s in manifest["shards"]] == [1, 1]
    one = _write(tmp_path / "one", recs, shard_bytes=256 << 20)
    assert [s["num_records"] for s in one["shards"]] == [2]


def test_writer_refuses_bad_input(tmp_path, records, make_record):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x.txt").write_text("x")
    with pytest.raises(DataError, match="not empty"):
        _write(tmp_path / "full", records)

    bad = make_record(seed=3)
    bad["depth"] = bad["depth"].astype(np.float64)
    with pytest.raises(DataError, match=r"record 2 \(ep000002\): key 'depth': expected dtype float32"):
        _write(tmp_path / "bad", records[:2] + [bad])
    assert list((tmp_path / "bad").iterdir()) == []           # nothing half-written left behind

    with pytest.raises(DataError, match="duplicate record key"):
        _write(tmp_path / "dup", [dict(records[0], __key__="a"), dict(records[1], __key__="a")])
    with pytest.raises(DataError, match="record key must match"):
        _write(tmp_path / "dot", [dict(records[0], __key__="a.b")])


def test_overwrite_replaces_the_dataset(tmp_path, records):
    _write(tmp_path / "ds", records)
    (tmp_path / "ds" / "notes.txt").write_text("kept")
    manifest = _write(tmp_path / "ds", records[:2], overwrite=True)
    names = sorted(p.name for p in (tmp_path / "ds").iterdir())
    assert names == ["manifest.json", "notes.txt", "shard-00000.tar"]
    assert manifest["num_records"] == 2 and len(ShardDataset(tmp_path / "ds", verify=True)) == 2


def test_interrupt_while_a_shard_is_being_opened_leaves_no_file(tmp_path, records, monkeypatch):
    """Ctrl-C after a shard's file is created but before its writer exists (CI hit this window once):
    the interrupt propagates and no file is left, neither the finished first shard nor the new one."""
    import core.data.shards.writer as shards

    opened = []
    real_open = tarfile.open

    def open_then_interrupt(*args, **kwargs):
        opened.append(1)
        if len(opened) == 2:  # the second shard's file exists now; its _ShardWriter is not assigned yet
            raise KeyboardInterrupt
        return real_open(*args, **kwargs)

    monkeypatch.setattr(shards.tarfile, "open", open_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        _write(tmp_path / "ds", records)
    assert len(opened) == 2 and list((tmp_path / "ds").iterdir()) == []


def test_interrupt_while_finishing_leaves_no_temporary_file(tmp_path, records, monkeypatch):
    """Ctrl-C between the shards' renames and the manifest's: no `.partial` file stays, and no manifest
    (the directory holds no dataset)."""
    import core.data.shards.writer as shards

    real_replace = shards.os.replace

    def replace_then_interrupt(src, dst):
        if str(dst).endswith(MANIFEST_NAME):
            raise KeyboardInterrupt
        return real_replace(src, dst)

    monkeypatch.setattr(shards.os, "replace", replace_then_interrupt)
    with pytest.raises(KeyboardInterrupt):
        _write(tmp_path / "ds", records)
    names = [p.name for p in (tmp_path / "ds").iterdir()]
    assert names and not [n for n in names if n.endswith(".partial") or n == MANIFEST_NAME], names


# ----------------------------------------------------------------------------- corruption

@pytest.fixture
def written(tmp_path, records):
    _write(tmp_path / "ds", records)
    return tmp_path / "ds"


def _one_line_error(fn) -> str:
    with pytest.raises(DataError) as err:
        fn()
    msg = str(err.value)
    assert "\n" not in msg
    return msg


def test_flipped_byte_fails_checksum_and_decode(written):
    path = written / "shard-00001.tar"
    data = bytearray(path.read_bytes())
    data[1500] ^= 0xFF                         # inside the first record's npz payload
    path.write_bytes(bytes(data))
    ds = ShardDataset(written)                 # same size: opening does not notice
    msg = _one_line_error(ds.verify)
    assert "shard-00001.tar" in msg and "sha256 mismatch" in msg
    # Random access does not hash, but the npz CRC or the schema still rejects the record.
    msg = _one_line_error(lambda: ds[2])
    assert msg.startswith("shard-00001.tar record ep000002:")


def test_truncated_shard(written):
    path = written / "shard-00002.tar"
    path.write_bytes(path.read_bytes()[:3000])
    msg = _one_line_error(lambda: ShardDataset(written))
    assert "shard-00002.tar" in msg and "truncated" in msg
    # The streaming reader (what Ray Data calls) also refuses, naming the shard and the record.
    keys = load_manifest(written)["shards"][2]["keys"]
    msg = _one_line_error(lambda: list(iter_shard(path, expected_keys=keys)))
    assert "shard-00002.tar" in msg and "truncated" in msg


def test_shard_truncated_at_a_member_boundary(written):
    path = written / "shard-00000.tar"
    with tarfile.open(path) as tar:
        second = tar.getmembers()[1].offset        # header of the second member
    path.write_bytes(path.read_bytes()[:second])
    keys = load_manifest(written)["shards"][0]["keys"]
    msg = _one_line_error(lambda: list(iter_shard(path, expected_keys=keys)))
    assert "shard-00000.tar" in msg and "1 of 2 records" in msg and "ep000001" in msg


def test_missing_shard(written):
    (written / "shard-00003.tar").unlink()
    msg = _one_line_error(lambda: ShardDataset(written))
    assert "missing shard shard-00003.tar" in msg
    msg = _one_line_error(lambda: list(iter_shard(written / "shard-00003.tar")))
    assert "missing shard shard-00003.tar" in msg


def test_missing_manifest_and_dir(tmp_path, written):
    assert "does not exist" in _one_line_error(lambda: ShardDataset(tmp_path / "nope"))
    (written / MANIFEST_NAME).unlink()
    assert "no manifest.json" in _one_line_error(lambda: ShardDataset(written))


def _rewrite_member(path, key: str, rec: dict, manifest_dir=None):
    """Rebuild a shard with `key`'s payload replaced by a bad record, and fix up the manifest so only
    the record-level check can catch it."""
    members = _naive_shard_contents(path)
    buf = io.BytesIO()
    np.savez(buf, **rec)
    members[f"{key}.npz"] = buf.getvalue()
    with tarfile.open(path, "w", format=tarfile.USTAR_FORMAT) as tar:
        for name, payload in members.items():
            info = tarfile.TarInfo(name)
            info.size = len(payload)
            tar.addfile(info, io.BytesIO(payload))
    manifest = json.loads((manifest_dir / MANIFEST_NAME).read_text())
    for entry in manifest["shards"]:
        if entry["filename"] == path.name:
            entry["bytes"] = path.stat().st_size
            entry["sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    (manifest_dir / MANIFEST_NAME).write_text(json.dumps(manifest))


def test_missing_key_in_a_record(written, records):
    rec = dict(records[5])
    del rec["box_id"]
    _rewrite_member(written / "shard-00002.tar", "ep000005", rec, written)
    ds = ShardDataset(written)
    msg = _one_line_error(ds.verify)
    assert msg == "shard-00002.tar record ep000005: key 'box_id' is missing"
    assert _one_line_error(lambda: ds[5]) == msg
    assert _one_line_error(lambda: list(ds)) == msg


def test_wrong_dtype_in_a_record(written, records):
    rec = dict(records[4])
    rec["rgb"] = rec["rgb"].astype(np.int16)
    _rewrite_member(written / "shard-00002.tar", "ep000004", rec, written)
    msg = _one_line_error(ShardDataset(written).verify)
    assert msg == "shard-00002.tar record ep000004: key 'rgb': expected dtype uint8, got int16"


def test_decode_record_rejects_pickles_and_garbage(records):
    where = "shard-00000.tar record x"
    assert "cannot decode npz" in _one_line_error(lambda: decode_record(b"garbage" * 10, where))
    buf = io.BytesIO()
    np.savez(buf, **dict(records[0], rgb=np.array([{"a": 1}], dtype=object)))
    msg = _one_line_error(lambda: decode_record(buf.getvalue(), where))
    assert msg.startswith(where) and "pickle" in msg
    _assert_same(decode_record(encode_record(records[0]), where), records[0])


def test_a_malformed_grid_or_dims_is_refused_by_name(written):
    path = written / MANIFEST_NAME
    good = json.loads(path.read_text())
    grid = {"Z": 8, "Y": 4, "X": 8, "xmin": -4.0, "xmax": 4.0, "ymin": -1, "ymax": 1, "zmin": 0.0, "zmax": 8.0}
    path.write_text(json.dumps({**good, "grid": grid, "dims": {"T": [2, 2], "V": [1, 4]}}))
    assert ShardDataset(written).manifest["grid"] == grid        # well-formed: read as written
    for field, bad in (("grid", {"Z": 1}), ("grid", {**grid, "X": 0}), ("grid", {**grid, "xmin": 5.0}),
                       ("grid", {**grid, "Y": 4.0}), ("grid", [8, 4, 8]),
                       ("dims", {"T": 5}), ("dims", {"T": [3, 2]}), ("dims", {"V": [1, "4"]}), ("dims", [2])):
        path.write_text(json.dumps({**good, field: bad}))
        msg = _one_line_error(lambda: ShardDataset(written))
        assert f"'{field}' is malformed" in msg and MANIFEST_NAME in msg, (field, bad, msg)
