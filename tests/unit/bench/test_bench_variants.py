"""Which detector rows a `bench paper` plan trains (BenchConfig.detector_variants): the small plan runs the rows
the detection claims read, `--detector-variants` chooses others, and a change of them touches only the dropped or
added rows' stages."""

from __future__ import annotations

from dataclasses import replace

import pytest

from services.bench.claims import CLAIM_DETECTOR_MODES
from services.bench.plan import DEFAULT_VARIANTS, JUDGED_VARIANTS, BenchConfigError, plan_for
from services.bench.replan import changed_stages
from services.cli.main import main


def test_the_small_plan_runs_exactly_the_rows_the_claims_read():
    assert set(JUDGED_VARIANTS) == {(arm, modes[0]) for arm, modes in CLAIM_DETECTOR_MODES.items()}
    assert plan_for("small").detector_variants == JUDGED_VARIANTS
    assert plan_for("tiny").detector_variants == DEFAULT_VARIANTS == plan_for("paper").detector_variants


def test_variants_must_be_known_and_distinct():
    with pytest.raises(BenchConfigError, match="'contrastive', 'thawed'"):
        plan_for("small", detector_variants=(("contrastive", "thawed"),))
    with pytest.raises(BenchConfigError, match="distinct"):
        plan_for("small", detector_variants=(("random", "finetuned"), ("random", "finetuned")))
    with pytest.raises(BenchConfigError, match="at least one"):
        plan_for("small", detector_variants=())


def test_dropping_rows_touches_only_their_detectors_and_evaluations(tmp_path):
    every = plan_for("tiny", quick=True, seeds=(0,), detector_variants=DEFAULT_VARIANTS)
    judged = replace(every, detector_variants=JUDGED_VARIANTS)
    changed = changed_stages(every, judged, tmp_path)
    dropped = [v for v in DEFAULT_VARIANTS if v not in JUDGED_VARIANTS]
    expected = {f"seed0/{prefix}{arm}_{mode}_L{budget}{draw}"
                for arm, mode in dropped for prefix in ("detector_", "eval/detection/")
                for budget, draws in (("2", ("", "_draw1")), ("all", ("",))) for draw in draws}
    assert set(changed) == expected and len(changed) == len(expected)


def test_cli_detector_variants_reach_the_plan_and_bad_ones_are_named(tmp_path, monkeypatch, capsys):
    import services.bench.paper as paper

    seen = {}
    monkeypatch.setattr(paper, "run_paper_bench", lambda config, out, **kw: seen.update(config=config) or {"claims": []})
    base = ["bench", "paper", "--seeds", "1", "--out", str(tmp_path / "r")]
    assert main(base) == 0 and seen["config"].detector_variants == JUDGED_VARIANTS
    assert main(base + ["--detector-variants", "random/finetuned", "contrastive/finetuned"]) == 0
    assert seen["config"].detector_variants == (("random", "finetuned"), ("contrastive", "finetuned"))
    with pytest.raises(SystemExit) as stop:
        main(base + ["--detector-variants", "contrastive"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and "--detector-variants" in err and "'contrastive' is not ARM/MODE" in err
    assert main(base + ["--detector-variants", "contrastive/thawed"]) != 0  # a BenchConfigError: one line
    assert "mode one of" in capsys.readouterr().err


def test_a_moving_iou_the_protocol_does_not_score_is_refused():
    # the protocol scores AP at 0.25, 0.33 and 0.5 only: 0.4 gave the moving claims no AP while the PR curve
    # quietly fell back to 0.5
    with pytest.raises(BenchConfigError, match=r"moving_iou must be one of \(0.25, 0.33, 0.5\).*0.4"):
        plan_for("small", moving_iou=0.4)
    assert plan_for("small", moving_iou=0.25).moving_iou == 0.25
