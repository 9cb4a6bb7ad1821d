"""`n3dmap train pretrain --workers 0` end to end on a tiny generated dataset (no Ray).

Trains the real pretrain task: the loss decreases, both objectives train and export a bundle that
`n3dmap bundle info` describes, and --init/--freeze-features warm-start from a bundle.
"""

import json

import pytest
import torch

from services.cli.main import main
from services.training.progress import read_metrics

pytestmark = pytest.mark.integration


def _train(data, run_dir, *extra) -> int:
    return main(["train", "pretrain", "--data", str(data), "--run-dir", str(run_dir), "--workers", "0",
                 "--device", "cpu", "--log-every", "1", *extra])


def test_regression_loss_decreases_and_bundle_is_described(tiny_train_data, tmp_path, capsys):
    torch.set_num_threads(1)
    run = tmp_path / "run"
    assert _train(tiny_train_data, run, "--objective", "regression", "--steps", "10", "--batch-size", "2",
                  "--lr", "3e-3", "--checkpoint-every", "5") == 0
    out = capsys.readouterr().out
    assert "step 10/10 (100%)" in out and "steps/s" in out and "ETA" in out

    losses = [r["loss"] for r in read_metrics(run / "metrics.jsonl")]
    assert len(losses) == 10
    assert sum(losses[-3:]) / 3 < sum(losses[:3]) / 3, losses

    assert main(["bundle", "info", str(run / "bundle"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["preset"] == "tiny" and info["grid"]["Z"] == 32
    assert {"mapper", "projector", "occupancy"} <= set(info["modules"])
    assert all(m["parameters"] > 0 for m in info["modules"].values())
    prov = info["provenance"]
    assert prov["task"] == "pretrain" and prov["objective"] == "regression" and prov["steps"] == 10
    assert prov["workers"] == 0 and prov["data_seed"] == 1000
    assert prov["data_manifest"] == str(tiny_train_data / "manifest.json")
    assert info["metrics"]["last_loss"] == pytest.approx(losses[-1], rel=1e-6)
    assert info["metrics"]["mean_loss"] == pytest.approx(sum(losses) / len(losses), rel=1e-5)

    assert main(["bundle", "info", str(run / "bundle")]) == 0
    text = capsys.readouterr().out
    assert "preset   tiny" in text and "mapper" in text


def test_contrastive_trains_then_warm_starts_a_frozen_run(tiny_train_data, tmp_path, capsys):
    from core.bundle import load_bundle

    torch.set_num_threads(1)
    first = tmp_path / "contrastive"
    assert _train(tiny_train_data, first, "--steps", "2", "--batch-size", "2") == 0
    records = read_metrics(first / "metrics.jsonl")
    assert [r["step"] for r in records] == [1, 2]
    assert all(k in records[0] for k in ("loss_2d", "loss_3d")), records[0]
    parent = load_bundle(first / "bundle")
    assert parent.meta["provenance"]["objective"] == "contrastive"

    # A regression task cannot take the contrastive projector (E=8 vs RGB): one clear line.
    assert _train(tiny_train_data, tmp_path / "bad", "--objective", "regression", "--steps", "1",
                  "--init", str(first / "bundle")) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("n3dmap train: error: --init") and "'projector' does not fit" in err
    assert "\n" not in err

    second = tmp_path / "frozen"
    assert _train(tiny_train_data, second, "--steps", "2", "--batch-size", "2",
                  "--init", str(first / "bundle"), "--freeze-features") == 0
    child = load_bundle(second / "bundle")
    for key, value in parent.modules["mapper"].state_dict().items():
        assert torch.equal(child.modules["mapper"].state_dict()[key], value), key  # frozen: unchanged
    changed = [k for k, v in parent.modules["projector"].state_dict().items()
               if not torch.equal(child.modules["projector"].state_dict()[k], v)]
    assert changed  # the rest trained on
    prov = child.meta["provenance"]
    assert prov["init_bundle"] == str(first / "bundle") and prov["frozen"] == ["mapper"]
    assert prov["parents"][0]["provenance"]["objective"] == "contrastive"
    capsys.readouterr()

    # `bundle info` prints the lineage one run per line: this run, then the bundle it started from.
    assert main(["bundle", "info", str(second / "bundle")]) == 0
    lines = capsys.readouterr().out.splitlines()
    at = lines.index(next(line for line in lines if line.startswith("  lineage")))
    assert lines[at + 1].startswith("    pretrain(objective=contrastive)  2 steps, seed 0, frozen mapper | data ")
    assert lines[at + 2].startswith("    <- pretrain(objective=contrastive)  2 steps, seed 0 | data ")
    assert f"| run {first} | git " in lines[at + 2] and not lines[at + 3].startswith("    ")
