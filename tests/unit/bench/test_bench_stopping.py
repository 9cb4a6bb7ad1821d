"""Stopping rules: the plateau decision against a plain loop over hand-built loss histories, the epochs
rule's step counts, and `train_by_rule` driving a fake trainer (real files, no model) through a cut-off
and a resume."""

import json
import math

import pytest

from services.bench.stopping import (
    MARKER, SELECTED, Evaluation, StageRule, StageRuleError, plateau_decision, train_by_rule,
)

RULE = StageRule(kind="plateau", eval_every=10, patience=2, min_improvement=0.1, min_steps=20, max_steps=100)


def reference_stop(rule, losses):
    """The rule read aloud: walk the evaluations; the best moves only on a ≥ min_improvement relative
    drop; stop at max_steps, or once past min_steps with `patience` evaluations since the best."""
    best, best_i, history = None, None, []
    for i, loss in enumerate(losses):
        step = (i + 1) * rule.eval_every
        history.append(step)
        if best is None or loss < best * (1 - rule.min_improvement):
            best, best_i = loss, i
        if step >= rule.max_steps:
            return step, (best_i + 1) * rule.eval_every
        if step >= rule.min_steps and i - best_i >= rule.patience:
            return step, (best_i + 1) * rule.eval_every
    return None, None


@pytest.mark.parametrize("losses", [
    [5.0, 4.0, 3.0, 2.9, 2.8, 2.7, 2.6],     # small drops (< 10 %) after step 30: stops at 50
    [5.0, 5.0, 5.0, 1.0, 0.5, 0.4, 0.39],    # flat at first, but min_steps keeps it going
    [5.0, 4.0, 3.0, 2.0, 1.5, 1.0, 0.8, 0.6, 0.5, 0.4],   # keeps improving: reaches max_steps
    [1.0, 2.0, 3.0],                          # only worse: stops at min_steps + patience
])
def test_plateau_decision_matches_the_reference(losses):
    want_stop, want_best = reference_stop(RULE, losses)
    got = None
    for n in range(1, len(losses) + 1):
        history = [Evaluation(step=(i + 1) * 10, loss=l) for i, l in enumerate(losses[:n])]
        stop, best, _ = plateau_decision(RULE, history)
        if stop:
            got = (history[-1].step, best)
            break
    assert got == (want_stop, want_best)


def test_non_finite_held_out_loss_never_becomes_the_best():
    history = [Evaluation(10, 3.0), Evaluation(20, math.nan), Evaluation(30, math.inf)]
    stop, best, reason = plateau_decision(RULE, history)
    assert stop and best == 10 and "since step 10" in reason


def test_epochs_rule_counts_passes_over_the_records():
    rule = StageRule(kind="epochs", epochs=40, min_steps=30, max_steps=1000)
    assert rule.epoch_steps(2, 2) == 40          # 1 step per epoch
    assert rule.epoch_steps(8, 2) == 160
    assert rule.epoch_steps(9, 2) == 200         # ceil(9/2) = 5 steps per epoch
    assert rule.epoch_steps(48, 2) == 960
    assert rule.epoch_steps(64, 2) == 1000       # clamped to max_steps
    assert StageRule(kind="epochs", epochs=1, min_steps=30, max_steps=100).epoch_steps(2, 2) == 30


def test_rules_reject_inconsistent_settings():
    for bad in (dict(kind="plateau", max_steps=10, eval_every=0, patience=1),
                dict(kind="epochs", max_steps=10, epochs=0), dict(kind="fixed", max_steps=10, min_steps=20),
                dict(kind="sometimes", max_steps=10)):
        with pytest.raises(StageRuleError):
            StageRule(**bad)


def test_a_rule_without_a_weight_average_keeps_the_dict_of_plans_written_before_the_field():
    # a plan.json rule of an earlier n3dmap (no ema_decay): it reads back and writes the same dict, so the
    # stage's digest is unchanged and `--rerun-changed` leaves the stage alone
    earlier = {"kind": "plateau", "max_steps": 2000, "min_steps": 200, "eval_every": 100, "patience": 3,
               "min_improvement": 0.01, "epochs": 0}
    assert StageRule(**earlier).to_dict() == earlier
    averaged = StageRule(**earlier, ema_decay=0.995)
    assert averaged.to_dict() == {**earlier, "ema_decay": 0.995}
    assert StageRule(**averaged.to_dict()) == averaged
    assert averaged.describe().endswith("; weights: moving average, decay 0.995")
    with pytest.raises(StageRuleError, match="ema_decay must lie in"):
        StageRule(**earlier, ema_decay=1.0)


class FakeTrainer:
    """Stands in for run_training: 'trains' by writing a bundle whose content names the step."""

    def __init__(self, run_dir, losses):
        self.run_dir, self.losses, self.calls = run_dir, losses, []

    def train_to(self, steps):
        self.calls.append(steps)
        bundle = self.run_dir / "bundle"
        bundle.mkdir(parents=True, exist_ok=True)
        (bundle / "bundle.json").write_text(json.dumps({"step": steps}))
        return bundle

    def loss(self, step):
        return self.losses[step // 10 - 1]


def test_train_by_rule_keeps_the_best_bundle_and_writes_the_marker_last(tmp_path):
    losses = [5.0, 4.0, 3.0, 2.9, 2.8, 2.7]
    fake = FakeTrainer(tmp_path, losses)
    result = train_by_rule(RULE, tmp_path, train_to=fake.train_to, heldout_loss=fake.loss, records=8, batch_size=2,
                           log=lambda _: None)
    assert fake.calls == [10, 20, 30, 40, 50]
    assert result["steps_run"] == 50 and result["selected_step"] == 30
    assert json.loads((tmp_path / SELECTED / "bundle.json").read_text()) == {"step": 30}
    assert json.loads((tmp_path / MARKER).read_text())["selected_step"] == 30


def test_train_by_rule_resumes_from_its_recorded_evaluations(tmp_path):
    losses = [5.0, 4.0, 3.0, 2.9, 2.8, 2.7]

    class Cut(Exception):
        pass

    first = FakeTrainer(tmp_path, losses)

    def dies_at_40(step):
        if step == 40:
            raise Cut()
        return first.loss(step)

    with pytest.raises(Cut):
        train_by_rule(RULE, tmp_path, train_to=first.train_to, heldout_loss=dies_at_40, records=8, batch_size=2,
                      log=lambda _: None)
    assert not (tmp_path / MARKER).exists()
    second = FakeTrainer(tmp_path, losses)
    result = train_by_rule(RULE, tmp_path, train_to=second.train_to, heldout_loss=second.loss, records=8,
                           batch_size=2, log=lambda _: None)
    assert second.calls == [40, 50]            # 10–30 were evaluated before the cut
    assert result["selected_step"] == 30 and [e["step"] for e in result["evaluations"]] == [10, 20, 30, 40, 50]


def test_fixed_and_epochs_rules_train_once(tmp_path):
    fake = FakeTrainer(tmp_path, [])
    result = train_by_rule(StageRule(kind="epochs", epochs=3, min_steps=1, max_steps=100), tmp_path,
                           train_to=fake.train_to, heldout_loss=None, records=9, batch_size=2, log=lambda _: None)
    assert fake.calls == [15] and result["steps_run"] == 15 and (tmp_path / SELECTED / "bundle.json").exists()


def test_the_selected_bundle_is_flushed_to_disk_before_it_becomes_the_selection(tmp_path, monkeypatch):
    """Every file of the copied bundle and its folder are fsynced before the rename that makes it RUN_DIR/selected,
    and the run folder after it: the held-out history and the marker that name the selection are fsynced, so a
    power loss must not leave them pointing at empty weights."""
    import os

    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (events.append(("fsync", os.readlink(f"/proc/self/fd/{fd}"))),
                                                 real_fsync(fd))[1])
    monkeypatch.setattr(os, "replace", lambda a, b: (events.append(("replace", str(a), str(b))), real_replace(a, b))[1])
    fake = FakeTrainer(tmp_path, [])
    train_by_rule(StageRule(kind="fixed", max_steps=7), tmp_path, train_to=fake.train_to, heldout_loss=None,
                  records=4, batch_size=2, log=lambda _: None)
    selected = tmp_path / SELECTED
    rename = next(i for i, e in enumerate(events) if e[0] == "replace" and e[2] == str(selected))
    staged = events[rename][1]
    flushed = {e[1] for e in events[:rename] if e[0] == "fsync"}
    assert {os.path.join(staged, "bundle.json"), staged} <= flushed
    assert ("fsync", str(tmp_path)) in events[rename:]
