"""Mean ± std over seeds, and the tables of the paper rebuilt from per-seed results.

`per_seed` is `{seed: result}` as `services.bench.paper` collects it; every function here returns
plain dicts of `Spread` values (`{"mean", "std", "n", "values"}`), NaN-free (missing values are left
out; a quantity no seed produced has mean None).
"""

from __future__ import annotations

import math
from typing import Iterable


def spread(values: Iterable) -> dict:
    """{"mean", "std" (population, 0 for one seed), "n", "values"} of the finite values."""
    vals = [float(v) for v in values if v is not None and isinstance(v, (int, float)) and math.isfinite(v)]
    if not vals:
        return {"mean": None, "std": None, "n": 0, "values": []}
    mean = sum(vals) / len(vals)
    std = math.sqrt(sum((v - mean) ** 2 for v in vals) / len(vals))
    return {"mean": mean, "std": std, "n": len(vals), "values": vals}


def fmt(s: dict | None, digits: int = 3) -> str:
    """'0.512 ± 0.031' (± only with several seeds); '–' when missing."""
    if not s or s.get("mean") is None:
        return "–"
    text = f"{s['mean']:.{digits}f}"
    if s["n"] > 1:
        text += f" ± {s['std']:.{digits}f}"
    return text


def get_path(d: dict, *path):
    """d[path[0]][path[1]]..., or None where a key is missing."""
    for key in path:
        if not isinstance(d, dict) or key not in d:
            return None
        d = d[key]
    return d


def over_seeds(per_seed: dict, *path) -> dict:
    return spread(get_path(r, *path) for r in per_seed.values())


def detection_table(per_seed: dict, variants, budgets: list[str], ious=("0.33", "0.5", "0.75")) -> dict:
    """{"arm/mode": {budget: {iou: Spread}}}."""
    return {f"{a}/{m}": {b: {i: over_seeds(per_seed, "detection", f"{a}/{m}/{b}", "map", i) for i in ious}
                         for b in budgets} for a, m in variants}


def detection_draws_table(per_seed: dict, variants, budget: str, draws: int, iou: str = "0.5") -> dict:
    """{"arm/mode": [Spread over seeds of draw d's mAP@iou, for d < draws]} at `budget` (the label draws'
    budget), plus "contrastive − regression (frozen)" and "(fine-tuned)": those differences per draw where
    both rows of a mode exist (the few-label claim reads the frozen one: services.bench.claims)."""
    def draw_maps(r: dict, variant: str) -> list:
        found = get_path(r, "detection", f"{variant}/{budget}", "draws") or []
        return [d.get(iou) for d in found] + [None] * (draws - len(found))

    # {variant: [each seed's mAP per draw]}, read once
    maps = {f"{a}/{m}": [draw_maps(r, f"{a}/{m}") for r in per_seed.values()] for a, m in variants}
    for mode, label in (("frozen", "frozen"), ("finetuned", "fine-tuned")):
        contrastive, regression = maps.get(f"contrastive/{mode}"), maps.get(f"regression/{mode}")
        if contrastive and regression:
            maps[f"contrastive − regression ({label})"] = [
                [None if c is None or g is None else c - g for c, g in zip(cs, gs)]
                for cs, gs in zip(contrastive, regression)]
    return {variant: [spread(seed[d] for seed in seeds) for d in range(draws)] for variant, seeds in maps.items()}


def retrieval_table(per_seed: dict, arms) -> dict:
    return {arm: {dim: {k: over_seeds(per_seed, "retrieval", arm, dim, k) for k in ("p@1", "p@5", "p@10")}
                  for dim in ("2d", "3d")} for arm in arms}


# The flow evaluation's other gates (core.eval.protocols.flow, core.pipeline.flow_gate), as extra rows "ARM, SUFFIX".
# Why: each arm's flow is gated by its own pretraining's occupancy head, so the gated rows (the claims' and the
# pipelines') compare the gates as much as the flow modules; the ungated rows compare the flow modules alone.
FLOW_GATE_ROWS = {"model_filled": "filled gate", "model_raw": "no gate"}


def flow_table(per_seed: dict, arms) -> dict:
    """Rows "zero-motion", one per arm (flow over that arm's features, free voxels zeroed), when run "input
    volumes" (flow over the fused input volumes), then for each of those that some seed evaluated with the
    other gates, "ARM, filled gate" and "ARM, no gate" (FLOW_GATE_ROWS): full/static/moving L1 EPE."""
    cols = {"full": "epe_l1_full", "static": "epe_l1_static", "moving": "epe_l1_moving", "epe3d": "epe3d"}
    rows = {"zero-motion": {c: over_seeds(per_seed, "flow", arms[-1], "zero_motion", k) for c, k in cols.items()}}
    sources = {arm: arm for arm in arms}
    if any(get_path(r, "flow", "volume") for r in per_seed.values()):
        # n3dmap's default flow module, over the fused input volumes instead of an arm's features
        sources["input volumes"] = "volume"
    for row, key in sources.items():
        rows[row] = {c: over_seeds(per_seed, "flow", key, "model", k) for c, k in cols.items()}
    for row, key in sources.items():
        for gate, suffix in FLOW_GATE_ROWS.items():
            if any(get_path(r, "flow", key, gate) for r in per_seed.values()):
                rows[f"{row}, {suffix}"] = {c: over_seeds(per_seed, "flow", key, gate, k) for c, k in cols.items()}
    return rows


def occupancy_table(per_seed: dict, rows) -> dict:
    """{row: {score: over seeds}} for the occupancy rows some seed has (plan.OCCUPANCY_ROWS, in that order)."""
    keys = ("acc_occupied", "acc_free", "acc_all", "iou_occupied", "threshold")
    present = [row for row in rows if any(get_path(r, "occupancy", row) for r in per_seed.values())]
    return {row: {k: over_seeds(per_seed, "occupancy", row, k) for k in keys} for row in present}


def egomotion_table(per_seed: dict) -> dict:
    methods = set()
    for r in per_seed.values():
        methods |= set(get_path(r, "egomotion", "methods") or {})
    # the model's own rows ("model", then e.g. "model, learned stages only"), then the baselines
    first = ["model", *sorted(m for m in methods if m.startswith("model,")), "icp", "identity"]
    order = [m for m in first if m in methods] + sorted(methods - set(first))
    return {m: {"rot_rad": over_seeds(per_seed, "egomotion", "methods", m, "rot_err_rad_mean"),
                "trans_m": over_seeds(per_seed, "egomotion", "methods", m, "trans_err_m_mean"),
                "pairs": over_seeds(per_seed, "egomotion", "methods", m, "pairs")} for m in order}


def moving_table(per_seed: dict) -> dict:
    """{setting: {method: {"ap": Spread, "ap_iou025": Spread, "gt_boxes": Spread, "curve": first seed's PR curve}}}."""
    out: dict = {}
    for setting in ("static", "moving"):
        methods: list[str] = []
        for r in per_seed.values():
            for m in get_path(r, "moving", setting) or {}:
                if m not in methods:
                    methods.append(m)
        methods.sort(key=_moving_order)
        first = next(iter(per_seed.values()), {})
        out[setting] = {m: {"ap": over_seeds(per_seed, "moving", setting, m, "ap"),
                            # AP at 3D IoU 0.25 too: boxes fitted to 0.5–1 m voxels rarely reach 0.5
                            "ap_iou025": over_seeds(per_seed, "moving", setting, m, "ap_by_iou", "0.25"),
                            "gt_boxes": over_seeds(per_seed, "moving", setting, m, "gt_boxes"),
                            "curve": get_path(first, "moving", setting, m, "curve")} for m in methods}
        out[f"pairs_{setting}"] = over_seeds(per_seed, "moving", "pairs", setting)
    return out


def _moving_order(method: str) -> tuple[int, str]:
    """Our models first, then the 2.5D baselines, then the oracle rows (upper bounds)."""
    rank = 2 if "oracle" in method else 1 if method.startswith("2.5D") else 0
    return rank, method
