"""`n3dmap data` error paths run in-process through services.cli.main.main (the real argparse tree and
error printing, without a subprocess per case): exit 2 and exactly one stderr line, no traceback."""

from __future__ import annotations

import json

import numpy as np
import pytest

import services.cli.main as cli_main
from core.data.shards import write_dataset

GRID = {"xmin": -16.0, "xmax": 16.0, "ymin": -4.0, "ymax": 4.0, "zmin": -16.0, "zmax": 16.0,
        "Z": 32, "Y": 8, "X": 32}


@pytest.fixture
def dataset(tmp_path, make_record):
    out = tmp_path / "d"
    write_dataset(out, [make_record(K=i % 3, seed=i) for i in range(5)], split="val", preset_name="tiny", grid=GRID,
                  generator={"source": "test"}, seed=1, shard_bytes=9000)
    return out


def run(capsys, *args):
    code = cli_main.main(["data", *map(str, args)])
    out, err = capsys.readouterr()
    return code, out, err


def expect_error(capsys, *args, fragments=()):
    code, _, err = run(capsys, *args)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and lines[0].startswith("n3dmap data: error: "), (code, err)
    for f in fragments:
        assert f in lines[0], lines[0]


def test_info_prints_the_manifest_summary(capsys, dataset):
    code, out, _ = run(capsys, "info", dataset, "--verify")
    assert code == 0
    for text in ("split      val", "preset     tiny", "records    5 in 3 shards", "K=0–2", "seed       1",
                 "shard-00002.tar", "verified   5 records in 3 shards"):
        assert text in out, out
    code, out, _ = run(capsys, "info", dataset, "--json")
    summary = json.loads(out)
    assert code == 0 and summary["num_records"] == 5 and "keys" not in summary["shards"][0]


def test_error_paths(capsys, dataset, tmp_path):
    expect_error(capsys, "info", tmp_path / "nope", fragments=["does not exist"])
    expect_error(capsys, "info", tmp_path, fragments=["no manifest.json"])
    expect_error(capsys, "preview", dataset, "--out", tmp_path / "p.png", "--index", 99,
                 fragments=["out of range"])
    expect_error(capsys, "generate", "--preset", "tiny", "--episodes", 1, "--out", dataset,
                 fragments=["is not empty", "--overwrite"])
    expect_error(capsys, "import", "tum", tmp_path / "nope", "--out", tmp_path / "o",
                 fragments=["does not exist"])
    text = tmp_path / "notes.txt"
    text.write_text("not an archive\n")
    expect_error(capsys, "import", "tum", text, "--out", tmp_path / "o", fragments=["is a file", "directory"])
    expect_error(capsys, "import", "authors-npz", text, "--out", tmp_path / "o",
                 fragments=["notes.txt is not an .npz archive"])
    (dataset / "shard-00001.tar").unlink()
    expect_error(capsys, "info", dataset, "--verify", fragments=["missing shard shard-00001.tar"])
    expect_error(capsys, "preview", dataset, "--out", tmp_path / "p.png", fragments=["missing shard"])


def test_import_authors_npz_via_cli(capsys, tmp_path):
    # A minimal authors' npz: one view, one point, no boxes.
    K = np.eye(4, dtype=np.float32)
    K[0, 0] = K[1, 1] = 2.0
    K[0, 2], K[1, 2] = 1.0, 1.0
    np.savez(tmp_path / "one.npz", pix_T_cams=K[None], origin_T_camXs=np.eye(4, dtype=np.float32)[None],
             origin_T_camRs=np.eye(4, dtype=np.float32)[None], rgb_camXs=np.zeros((1, 3, 3, 3), np.uint8),
             xyz_camXs=np.array([[[0, 0, 2]]], np.float32), boxlists=np.zeros((1, 0, 9), np.float32),
             tidlists=np.zeros((1, 0), np.int32), scorelists=np.zeros((1, 0), np.float32))
    code, out, _ = run(capsys, "import", "authors-npz", tmp_path / "one.npz", "--out", tmp_path / "imp",
                       "--preset", "tiny")
    assert code == 0 and "wrote 1 records" in out
    code, out, _ = run(capsys, "info", tmp_path / "imp", "--verify")
    assert code == 0 and "verified   1 records" in out
