"""services.training.config.init_mapper_options: a warm-started task builds the init bundle's mapper shape."""

import pytest

from core.bundle import save_bundle
from core.models.latent_map import Mapper
from core.presets import TINY
from services.training.config import TrainJobConfig, init_mapper_options


@pytest.fixture(scope="module")
def full_res_bundle(tmp_path_factory):
    out = tmp_path_factory.mktemp("b") / "bundle"
    mapper = Mapper(grid=TINY.grid, width=TINY.encoder_width, feature_dim=TINY.feature_dim, full_res=4)
    save_bundle(out, modules={"mapper": mapper}, preset=TINY)
    return str(out)


def test_mapper_tasks_take_the_bundles_full_res_branch(full_res_bundle):
    for task in ("flow", "occupancy", "detector", "pretrain"):
        assert init_mapper_options(task, {"inputs": "features"}, full_res_bundle) == {
            "inputs": "features", "encoder_full_res": 4}
    assert init_mapper_options("flow", {"encoder_full_res": 8}, full_res_bundle) == {"encoder_full_res": 8}
    assert init_mapper_options("egomotion", {}, full_res_bundle) == {}  # builds no mapper
    assert init_mapper_options("flow", {}, None) == {}
    # resolved configs carry it, so the stored config says what ran
    config = TrainJobConfig(task="flow", data_dir="d", run_dir="r", task_options={"inputs": "features"},
                            init_bundle=full_res_bundle).resolved()
    assert config.task_options == {"inputs": "features", "encoder_full_res": 4}


def test_a_bundle_of_the_papers_layers_adds_nothing(tmp_path):
    mapper = Mapper(grid=TINY.grid, width=TINY.encoder_width, feature_dim=TINY.feature_dim)
    save_bundle(tmp_path / "b", modules={"mapper": mapper}, preset=TINY)
    assert init_mapper_options("flow", {"inputs": "volume"}, str(tmp_path / "b")) == {"inputs": "volume"}
