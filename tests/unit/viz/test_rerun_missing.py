"""Without the viz extra (rerun-sdk not importable), every command asked for a Rerun recording prints
one line naming the extra and exits 2, before doing any work; the commands that need no recording
are unaffected (their modules never import rerun)."""

from __future__ import annotations

import sys

import pytest

import services.cli.main as cli_main

HINT = "install the viz extra: pip install -e '.[viz]'"


@pytest.fixture
def no_rerun(monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # `import rerun` now raises ImportError


@pytest.mark.parametrize("argv", [
    ["data", "preview", "{tmp}/missing-dataset", "--rerun", "{tmp}/p.rrd"],
    ["eval", "moving", "--data", "{tmp}/d", "--bundle", "{tmp}/b", "--out", "{tmp}/r", "--rerun", "{tmp}/m.rrd"],
    ["eval", "flow", "--data", "{tmp}/d", "--bundle", "{tmp}/b", "--out", "{tmp}/r", "--rerun", "{tmp}/f.rrd"],
    ["eval", "detection", "--data", "{tmp}/d", "--bundle", "{tmp}/b", "--out", "{tmp}/r", "--rerun", "{tmp}/d.rrd"],
    ["stream", "view", "--camera-id", "cam0", "--save", "{tmp}/s.rrd"],
    ["stream", "view", "--camera-id", "cam0", "--serve-web", "9090"],
], ids=lambda a: " ".join(a[:2]) + (" " + a[-2] if a[0] == "stream" else ""))
def test_commands_say_how_to_install_the_extra(no_rerun, capsys, tmp_path, argv):
    code = cli_main.main([a.format(tmp=tmp_path) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0] == f"n3dmap {argv[0]}: error: {HINT}" or err[0].startswith(f"n3dmap {argv[0]}: error: {HINT} ("), err
    assert not list(tmp_path.iterdir()), "nothing was written"


def test_preview_png_needs_no_rerun(no_rerun, capsys, tmp_path, make_record):
    from core.data.shards import write_dataset

    grid = {"xmin": -16.0, "xmax": 16.0, "ymin": -4.0, "ymax": 4.0, "zmin": -16.0, "zmax": 16.0, "Z": 32, "Y": 8, "X": 32}
    write_dataset(tmp_path / "d", [make_record(seed=0)], split="val", preset_name="tiny", grid=grid,
                  generator={"source": "test"}, seed=0, shard_bytes=1 << 20)
    assert cli_main.main(["data", "preview", str(tmp_path / "d"), "--out", str(tmp_path / "p.png")]) == 0
    assert (tmp_path / "p.png").stat().st_size > 1000
