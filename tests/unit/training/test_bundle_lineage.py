"""`n3dmap bundle info`: the lineage as one readable line per run (this bundle's, then each ancestor's),
`--json` the full nested record. The bundles are cheap (one 1×1×1 conv each) but carry the provenance
that training writes (services.training.job.run_provenance + core.bundle.parent_provenance)."""

import json
from pathlib import Path

from services.cli.main import main


def _bundle(out: Path, task: str, options: dict, *, steps: int, parent: Path | None = None,
            freeze: tuple[str, ...] = (), precision: str = "fp32") -> Path:
    from core.bundle import load_bundle, parent_provenance, save_bundle
    from core.models.registry import build_module
    from core.presets import get_preset
    from services.training.config import TrainJobConfig
    from services.training.job import run_provenance

    run_dir = out.parent / f"run_{task}"
    config = TrainJobConfig(task=task, data_dir=str(out.parent / "data"), run_dir=str(run_dir), preset="tiny",
                            task_options=options, steps=steps, batch_size=2, lr=1e-3, seed=7,
                            init_bundle=str(parent) if parent else None, freeze=freeze, precision=precision)
    parents = [parent_provenance(load_bundle(parent))] if parent else []
    provenance = run_provenance(config, manifest={"seed": 1000, "split": "train"}, steps=steps, parents=parents)
    return save_bundle(out, modules={"occupancy": build_module("occupancy_head", {"in_channels": 2})},
                       preset=get_preset("tiny"), provenance=provenance, metrics={"last_loss": 0.5})


def _chain(tmp_path: Path) -> Path:
    """pretrain -> egomotion (bf16) -> occupancy -> detector: the detector bundle has three ancestors."""
    pre = _bundle(tmp_path / "pre", "pretrain", {"objective": "contrastive"}, steps=30)
    ego = _bundle(tmp_path / "ego", "egomotion", {"augment": True, "augment_deg": 6.0, "augment_m": 1.0},
                  steps=20, parent=pre, precision="bf16")
    occ = _bundle(tmp_path / "occ", "occupancy", {"input_views": 2}, steps=10, parent=ego)
    return _bundle(tmp_path / "det", "detector", {"freeze_features": True}, steps=5, parent=occ, freeze=("mapper",))


def _lineage(text: str) -> list[str]:
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("  lineage"))
    out = []
    for line in lines[start + 1:]:
        if not line.startswith("    "):  # the next section ("  metrics")
            break
        out.append(line)
    return out


def test_lineage_is_one_line_per_run_newest_first(tmp_path, capsys):
    from services.training.job import git_commit

    det = _chain(tmp_path)
    assert main(["bundle", "info", str(det)]) == 0
    text = capsys.readouterr().out
    lineage = _lineage(text)
    assert len(lineage) == 4, text
    assert lineage[0].startswith("    detector(freeze_features=True)  5 steps, seed 7, frozen mapper | ")
    assert lineage[1].startswith("    <- occupancy(input_views=2)  10 steps, seed 7 | ")
    assert lineage[2].startswith("      <- egomotion(augment=True, augment_deg=6, augment_m=1)  "
                                 "20 steps, seed 7, bf16 | ")
    assert lineage[3].startswith("        <- pretrain(objective=contrastive)  30 steps, seed 7 | ")
    commit = git_commit()
    for line, task in zip(lineage, ("detector", "occupancy", "egomotion", "pretrain")):
        assert f"| data {tmp_path / 'data'} (train, seed 1000) | " in line, line
        assert f"| run {tmp_path / f'run_{task}'} | " in line, line
        assert line.endswith(f"| git {commit[:10]}" if commit else "| git ?"), line
    assert "{" not in "\n".join(lineage)  # no nested JSON left
    assert "metrics" in text and "last_loss: 0.5" in text


def test_json_keeps_the_full_nested_record(tmp_path, capsys):
    det = _chain(tmp_path)
    assert main(["bundle", "info", str(det), "--json"]) == 0
    prov = json.loads(capsys.readouterr().out)["provenance"]
    tasks = []
    while True:
        tasks.append(prov["task"])
        assert prov["lr"] == 1e-3 and prov["workers"] == 0 and prov["batch_size_per_worker"] == 2
        if not prov["parents"]:
            break
        assert prov["init_bundle"] == prov["parents"][0]["path"]
        prov = prov["parents"][0]["provenance"]
    assert tasks == ["detector", "occupancy", "egomotion", "pretrain"]
    assert prov["objective"] == "contrastive"


def test_provenance_without_a_task_or_with_bad_parents_still_prints(tmp_path, capsys):
    from core.bundle import save_bundle
    from core.models.registry import build_module
    from core.presets import get_preset

    module = {"occupancy": build_module("occupancy_head", {"in_channels": 2})}
    plain = save_bundle(tmp_path / "plain", modules=module, preset=get_preset("tiny"), provenance={"test": "serve"})
    assert main(["bundle", "info", str(plain)]) == 0
    assert _lineage(capsys.readouterr().out) == [f"    (no task recorded) test=serve | bundle {plain}"]

    odd = save_bundle(tmp_path / "odd", modules=module, preset=get_preset("tiny"),
                      provenance={"task": "flow", "parents": ["not a dict", {"provenance": 3}]})
    assert main(["bundle", "info", str(odd)]) == 0
    assert _lineage(capsys.readouterr().out) == [
        f"    flow  bundle {odd} | git ?", "    <- (malformed parent entry)", "    <- (malformed provenance: int)"]
