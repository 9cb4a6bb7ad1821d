"""The 2.5D baselines' size priors are estimated from the same gated clusters the scored pairs use.

The scored 2.5D rows drop pixels at or below the pair's ground plane (core.baselines.flow2d, the 3D methods'
ground gate); a prior estimated from ungated clusters would count the road pixels Farneback's flow spills
onto and grow every baseline box. The reference is the ground the scored loop passes: the oracle row's.
"""

import numpy as np
import pytest

import core.eval.protocols.moving as moving
from core.eval.protocols.moving import MovingEvalConfig, baseline_priors
from core.eval.protocols.moving_oracle import oracle_boxes
from core.pipeline.moving import MovingObjectsConfig
from core.presets import TINY
from core.synthetic.generate import generate_record


@pytest.fixture(scope="module")
def records():
    return [generate_record(TINY, seed=s, num_frames=2, num_views=2) for s in (1, 2)]


def _spy(monkeypatch) -> list[tuple[int, int, object]]:
    calls = []
    real = moving.moving_objects_2p5d_rig

    def spy(record, t, **kw):
        calls.append((id(record), t, kw.get("ground")))
        return real(record, t, **kw)
    monkeypatch.setattr(moving, "moving_objects_2p5d_rig", spy)
    return calls


def test_priors_use_the_ground_plane_of_the_scored_pairs(records, monkeypatch):
    config = MovingEvalConfig()
    calls = _spy(monkeypatch)
    baseline_priors(records, TINY.grid, config)
    sources = {source for source, stabilise in moving.BASELINES.values() if stabilise}
    assert len(calls) == len(records) * len(sources)          # one call per pair and flow source
    by_record = {id(r): r for r in records}
    for record_id, t, ground in calls:
        want = oracle_boxes(by_record[record_id], t, TINY.grid, config.objects)["ground"]
        assert want is not None and ground is not None
        np.testing.assert_array_equal(np.asarray(ground), np.asarray(want))


def test_without_a_ground_gate_neither_the_priors_nor_the_scored_pairs_get_a_plane(records, monkeypatch):
    config = MovingEvalConfig(objects=MovingObjectsConfig(ground_margin=None))
    calls = _spy(monkeypatch)
    baseline_priors(records, TINY.grid, config)
    assert calls and all(ground is None for _, _, ground in calls)
    assert oracle_boxes(records[0], 0, TINY.grid, config.objects)["ground"] is None
