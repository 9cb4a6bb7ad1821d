"""BenchConfig.world: the benchmark's synthetic world (camera photometrics, texture scales), checked,
recorded in the plan, carried into the data stages' specs (so their digests) and into the records."""

import json
from dataclasses import replace

import numpy as np
import pytest

from core.data.shards import ShardDataset
from services.bench.data import generate_split
from services.bench.paper import _check_same_plan, _data_specs
from services.bench.plan import BenchConfig, BenchConfigError, plan_for
from services.bench.replan import stage_digests
from services.cli.main import main

CAMERA = {"exposure_std": 0.3, "pixel_noise_std": 0.03, "texture_scale": [0.1, 0.4]}


def test_world_round_trips_and_old_plans_read_as_the_presets_world():
    config = plan_for("tiny", quick=True, world=CAMERA)
    assert BenchConfig.from_dict(json.loads(json.dumps(config.to_dict()))) == config
    assert config.world_config().exposure_std == 0.3 and config.world_config().texture_scale == (0.1, 0.4)
    old = plan_for("tiny", quick=True).to_dict()
    del old["world"]
    assert BenchConfig.from_dict(old).world == {}


@pytest.mark.parametrize("world, message", [
    ({"exposure": 0.3}, r"unknown WorldConfig field\(s\) \['exposure'\]"),
    ({"pixel_noise_std": -1.0}, "pixel_noise_std must be a number >= 0"),
    ({"exposure_std": "high"}, "exposure_std must be a number"),
    ({"texture_scale": [0.5, 0.1]}, "texture_scale"),
    ({"texture_scale": [0.5]}, "texture_scale"),
])
def test_bad_worlds_are_refused_by_name(world, message):
    with pytest.raises(BenchConfigError, match=message):
        plan_for("tiny", quick=True, world=world)


def test_world_reaches_every_data_stage_and_no_spec_changes_without_it(tmp_path):
    plain = plan_for("tiny", quick=True, seeds=(0,))
    camera = replace(plain, world=CAMERA)
    assert all("world" not in spec for spec in _data_specs(plain).values())  # old digests kept
    assert all(spec["world"] == CAMERA for spec in _data_specs(camera).values())
    before, after = stage_digests(plain, tmp_path / "w"), stage_digests(camera, tmp_path / "w")
    assert before.keys() == after.keys()
    assert all(before[name] != after[name] for name in before)  # every stage reads the data


def test_a_rerun_must_keep_the_world(tmp_path):
    plan = tmp_path / "work" / "plan.json"
    plan.parent.mkdir(parents=True)
    old = plan_for("tiny", quick=True).to_dict()
    del old["world"]  # written before the field: the preset's world
    plan.write_text(json.dumps(old))
    _check_same_plan(plan, plan_for("tiny", quick=True))
    with pytest.raises(BenchConfigError, match="world"):
        _check_same_plan(plan, plan_for("tiny", quick=True, world=CAMERA))


def test_generate_split_renders_the_world(tmp_path):
    generate_split(tmp_path / "plain", preset="tiny", episodes=1, seed=4, split="val")
    manifest = generate_split(tmp_path / "camera", preset="tiny", episodes=1, seed=4, split="val", world=CAMERA)
    assert manifest["generator"]["world"] == CAMERA
    plain, camera = ShardDataset(tmp_path / "plain")[0], ShardDataset(tmp_path / "camera")[0]
    assert np.array_equal(plain["depth"], camera["depth"]) and not np.array_equal(plain["rgb"], camera["rgb"])


def test_cli_world_reaches_the_plan_and_bad_input_names_it(tmp_path, monkeypatch, capsys):
    import services.bench.paper as paper

    seen = {}
    monkeypatch.setattr(paper, "run_paper_bench", lambda config, out, **kw: seen.update(config=config) or {"claims": []})
    base = ["bench", "paper", "--quick", "--seeds", "1", "--out", str(tmp_path / "r")]
    assert main(base + ["--world", json.dumps(CAMERA)]) == 0
    assert seen["config"].world == CAMERA
    with pytest.raises(SystemExit) as stop:
        main(base + ["--world", "[1]"])
    assert stop.value.code == 2 and "--world" in capsys.readouterr().err
    assert main(base + ["--world", '{"exposure": 1}']) != 0  # a BenchConfigError: one line, no traceback
    assert "unknown WorldConfig field(s) ['exposure']" in capsys.readouterr().err


def test_moving_objects_are_scored_with_the_worlds_step(monkeypatch):
    """The boxes' speed threshold is m/s: the moving-object evaluation must turn it into voxels per pair with
    the world's dt, not the default 0.2 s (a world stepping 0.1 s halves every object's flow)."""
    from core.eval.protocols import moving as protocol
    from services.bench import evaluations

    seen = []

    def evaluate(bundle, records, config, *, device):   # records the config; no pairs to score
        seen.append(config.objects.dt)
        return {"pairs": {"static": 0, "moving": 0}, "acc": {}}
    monkeypatch.setattr(protocol, "evaluate", evaluate)
    config = plan_for("tiny", quick=True, world={"dt": 0.1})
    assert config.world_config().dt == 0.1
    evaluations.moving({"a": None, "b": None}, [], device="cpu", iou=0.5, threshold_px=1.0, min_pixels=15,
                       dt=config.world_config().dt)
    assert seen == [0.1, 0.1]
