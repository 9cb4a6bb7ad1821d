"""`n3dmap bundle flow-window`: a copy of a bundle whose flow module's full-grid step has another window. Checked
against the obvious reference — the same module built with the wide window from the start and given the same
weights: equal weights, equal flow on a random pair; every other module unchanged; bad input refused."""

import pytest
import torch

from core.bundle import load_bundle, save_bundle
from core.models.flow3d import Flow3D
from core.presets import TINY
from core.tasks import build_task
from services.cli.main import main


def _narrow_flow_bundle(path, *, with_mapper: bool = True):
    """mapper + an input-volume flow module with the pre-session-36 ±1 grid step (random weights, seeded)."""
    torch.manual_seed(3)
    task = build_task("flow", TINY, inputs="volume", refine_radius=(1, 1, 1), refine_aggregate=(0, 0, 0), seed=3)
    with torch.no_grad():   # a non-trivial step: the defaults' zero-init decoders would hide a lost weight
        for p in task.flow.parameters():
            p.add_(0.05 * torch.randn_like(p))
    modules = {"mapper": task.mapper, "flow": task.flow} if with_mapper else {"flow": task.flow}
    return save_bundle(path, modules=modules, preset=TINY, provenance={"task": "flow"})


def test_the_copy_is_the_wide_module_with_the_same_weights(tmp_path):
    src = _narrow_flow_bundle(tmp_path / "narrow")
    assert main(["bundle", "flow-window", str(src), "--out", str(tmp_path / "wide")]) == 0
    narrow, wide = load_bundle(src), load_bundle(tmp_path / "wide")
    net = wide.modules["flow"]
    assert net.refine_radius == (3, 1, 3) and tuple(net.refine_aggregate) == (1, 1, 1)
    # reference: the module built wide from the start, the narrow module's weights loaded into it
    reference = Flow3D(**{**narrow.modules["flow"].config(), "refine_radius": [3, 1, 3], "refine_aggregate": [1, 1, 1]})
    reference.load_state_dict(narrow.modules["flow"].state_dict())
    reference.eval()
    for key, value in reference.state_dict().items():
        assert torch.equal(net.state_dict()[key], value), key
    g = TINY.grid
    torch.manual_seed(0)
    v0, v1 = torch.rand(1, 4, g.Z, g.Y, g.X), torch.rand(1, 4, g.Z, g.Y, g.X)
    with torch.no_grad():
        out, ref, before = net(v0, v1)["flow"], reference(v0, v1)["flow"], narrow.modules["flow"](v0, v1)["flow"]
    assert torch.equal(out, ref)
    assert not torch.allclose(out, before)          # the window really changed what the step computes
    for key, value in narrow.modules["mapper"].state_dict().items():
        assert torch.equal(wide.modules["mapper"].state_dict()[key], value), key
    assert wide.meta["provenance"]["task"] == "flow-window"
    assert wide.meta["provenance"]["refine_radius"] == [3, 1, 3]


def test_a_chosen_window_and_box(tmp_path):
    src = _narrow_flow_bundle(tmp_path / "narrow", with_mapper=False)
    assert main(["bundle", "flow-window", str(src), "--out", str(tmp_path / "w2"), "--refine-radius", "2", "1", "2",
                 "--refine-aggregate", "0", "0", "0"]) == 0
    net = load_bundle(tmp_path / "w2").modules["flow"]
    assert net.refine_radius == (2, 1, 2) and tuple(net.refine_aggregate) == (0, 0, 0)


def test_bad_input_is_refused_and_writes_nothing(tmp_path, capsys):
    src = _narrow_flow_bundle(tmp_path / "narrow")
    assert main(["bundle", "flow-window", str(src), "--out", str(src)]) == 2                  # never in place
    assert "new directory" in capsys.readouterr().err
    torch.manual_seed(0)
    ego = build_task("egomotion", TINY, seed=0)
    no_flow = save_bundle(tmp_path / "ego", modules={"egomotion": ego.egomotion}, preset=TINY)
    assert main(["bundle", "flow-window", str(no_flow), "--out", str(tmp_path / "x")]) == 2
    assert "has no flow module" in capsys.readouterr().err and not (tmp_path / "x" / "bundle.json").exists()
    no_step = Flow3D(in_channels=4, inputs="volume", finest=0)
    plain = save_bundle(tmp_path / "plain", modules={"flow": no_step}, preset=TINY)
    assert main(["bundle", "flow-window", str(plain), "--out", str(tmp_path / "y")]) == 2
    assert "no full-grid step" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["bundle", "flow-window", str(src), "--out", str(tmp_path / "z"), "--refine-radius", "3", "-1", "3"])
