"""Train on a random subset of a record's camera views, so a module trained on multi-view records also
works on fewer views (the zenoh stream feeds one camera).

Why: a flow + egomotion chain trained 300 steps per task on 4-view small-preset records, evaluated on
32 single-view static-camera pairs (`n3dmap eval moving`): AP3D@0.5 0.001 with 429 boxes for 68 true
movers (0.35–0.40 on 4-view pairs); stabilised with the true poses instead of its egomotion module,
0.002 with 120 boxes. Inputs fused from one view are sparser than any the modules were trained on.

Measured with min_views 1 (flow, then egomotion, 300 steps each from the same occupancy bundle, seed 0):
on the single-view pairs, with a fixed size prior 4.3 × 1.9 × 1.65 m, flow stabilised by the true poses
AP3D@0.5 0.097 against 0.126 for flow trained on every view; with the chain's egomotion 0.111 (244 boxes)
against 0.139 (330 boxes) for the every-view chain (whose egomotion module is the older binary one, so
that pair differs in more than the views). No gain, so the tasks' default stays every view (None).

Per step one subset for the whole batch (every example and both time steps: a camera rig does not change
between frames), its size k uniform in [min_views, V], the views drawn without replacement.
"""

from __future__ import annotations

import torch

# Batch keys (core.data.batch) with a view axis, and where it is: B×T×V×… or B×V×….
VIEW_AXIS = {"rgb": 2, "depth": 2, "world_T_cam": 2, "pix_T_cam": 1}


def random_view_subset(batch: dict[str, torch.Tensor], *, min_views: int,
                       generator: torch.Generator | None) -> dict[str, torch.Tensor]:
    """batch with V views -> the same batch with k of them (k uniform in [min(min_views, V), V]), in
    their original order; keys without a view axis are passed through. min_views ≥ 1."""
    if min_views < 1:
        raise ValueError(f"min_views must be at least 1, got {min_views}")
    V = batch["rgb"].shape[2]
    low = min(min_views, V)
    k = low + int(torch.randint(V - low + 1, (1,), generator=generator))
    if k == V:
        return batch
    views = torch.randperm(V, generator=generator)[:k].sort().values  # k
    out = dict(batch)
    for key, axis in VIEW_AXIS.items():
        if key in batch:
            out[key] = batch[key].index_select(axis, views.to(batch[key].device))
    return out
