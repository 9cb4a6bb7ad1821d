"""The flow task's synthetic object motions: what the moved frame holds where the object was."""

import pytest
import torch

from core.data.batch import records_to_batch
from core.models import flow_synthetic
from core.presets import TINY
from core.synthetic.generate import generate_record
from core.tasks.flow import FlowTask


@pytest.mark.parametrize("inputs", ["volume", "features"])
def test_an_input_volume_leaves_empty_space_behind_a_moved_object_a_feature_map_its_old_content(inputs, monkeypatch):
    drawn, pairs = {}, []

    def record_draw(*args, **kwargs):
        drawn["motion"], drawn["block"] = flow_synthetic.sample_object_motions(*args, **kwargs)
        return drawn["motion"], drawn["block"]

    monkeypatch.setattr("core.tasks.flow.sample_object_motions", record_draw)
    batch = records_to_batch([generate_record(TINY, seed=3, num_frames=2)])
    for seed in range(50):   # a draw whose block held content and left some of its place behind
        pairs.clear()
        task = FlowTask.from_preset(TINY, seed=seed, inputs=inputs, object_fraction=1.0)
        task.flow.register_forward_hook(lambda module, args, out: pairs.append(args))
        task(batch)
        f0, moved = pairs[0]                     # the first call is the synthetic pair: B×C×Z×Y×X each
        landed = flow_synthetic.landing_place(drawn["block"], drawn["motion"], TINY.grid)  # B×1×Z×Y×X bool
        vacated = (drawn["block"] > 0.5) & ~landed & (f0.abs().sum(1, keepdim=True) > 0)   # B×1×Z×Y×X
        if int(vacated.sum()) > 0:
            break
    assert int(vacated.sum()) > 0
    vacated = vacated.expand_as(f0)
    if inputs == "volume":
        assert float(moved[vacated].abs().max()) == 0.0            # a real pair's vacated space is empty
    else:
        assert torch.equal(moved[vacated], f0[vacated])            # the background the object hid
