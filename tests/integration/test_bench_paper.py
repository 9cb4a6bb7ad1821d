"""`n3dmap bench paper --preset tiny --quick` as a real process, two seeds in two worker processes, with
per-stage task options (--task-options, reaching every stage they name): every stage runs, the report holds every table and metrics.json every key, each claim is stated with
its numbers per seed, the thread plan is printed and fits the CPUs, and a rerun skips every finished
stage (resume) while a changed plan is refused unless `--rerun-changed`, which redoes only the stages
the change touches. The quick profile trains for 2 steps per stage, so its report must give no verdicts:
every claim is "not judged" with `holds: null`.
"""

import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from core.data.shards import ShardDataset
from services.bench.report import METRIC_KEYS

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [pytest.mark.slow, pytest.mark.integration]

SECTIONS = ("## Semi-supervised 3D object detection: mAP vs number of labels", "## 2D and 3D patch retrieval",
            "## 3D flow: mean endpoint error in egomotion-stabilised scenes",
            "## Unsupervised 3D moving-object detection", "## Occupancy accuracy", "## Egomotion error",
            "## Claims", "## The learned chain's targets", "## Stages and wall time")
PLOTS = ("detection_map_vs_labels.png", "moving_pr_static_camera.png", "moving_pr_moving_camera.png")
CLAIMS = ("detection_few_labels", "detection_more_labels", "detection_gain_low_data", "retrieval_2d", "retrieval_3d",
          "flow_contrastive_vs_regression", "flow_vs_zero_motion", "moving_static_vs_2p5d",
          "moving_static_vs_regression", "moving_camera_stabilised", "occupancy_accuracy", "egomotion_vs_icp")


TASK_OPTIONS = {"mapper": {"encoder_full_res": 4}, "pretrain": {"coeff_match": 0.5},
                "pretrain_contrastive": {"shift_positives": 1},
                "flow_features": {"refine_radius": [2, 1, 2], "refine_aggregate": [1, 0, 1]}}  # not the defaults


def _bench_cmd(out: Path, options: dict = TASK_OPTIONS) -> list[str]:
    return [sys.executable, "-m", "services.cli.main", "bench", "paper", "--preset", "tiny", "--quick", "--seeds", "2",
            "--parallel-seeds", "2", "--out", str(out), "--device", "cpu", "--task-options", json.dumps(options)]


def _bench(out: Path, *, options: dict = TASK_OPTIONS, extra: tuple[str, ...] = (),
           check: bool = True) -> subprocess.CompletedProcess:
    proc = subprocess.run([*_bench_cmd(out, options), *extra], cwd=ROOT, capture_output=True, text=True, timeout=600)
    if check:
        assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc


def _rerun_seed1_egomotion_until_it_trains(out: Path) -> tuple[subprocess.Popen, Path, int]:
    """Start `bench paper --redo seed1/egomotion` on `out` and return (process, seed 1's worker log, the log's
    size before it) once that stage is running in its worker."""
    import time

    proc = subprocess.Popen([*_bench_cmd(out), "--redo", "seed1/egomotion"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    log = out / "work" / "seed1" / "worker.log"
    size = log.stat().st_size
    deadline = time.monotonic() + 120
    try:
        while "[bench] seed1/egomotion: running" not in log.read_text()[size:]:
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
    except BaseException:
        proc.kill()
        proc.wait()
        raise
    return proc, log, size


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench") / "report"
    first = _bench(out)
    return out, first


def test_report_has_every_table_plot_and_claim(bench_run):
    out, _ = bench_run
    report = (out / "report.md").read_text()
    for heading in SECTIONS:
        assert heading in report, heading
    for plot in PLOTS:
        assert (out / plot).stat().st_size > 0
        assert f"({plot})" in report
    # Detection rows: every variant of the quick plan, a column per label budget.
    for variant in ("random/finetuned", "regression/frozen", "contrastive/frozen", "contrastive/finetuned"):
        assert re.search(rf"\| {re.escape(variant)} \| [0-9.]+ ± [0-9.]+ \| [0-9.]+ ± [0-9.]+ \|", report), variant
    # Flow table: the zero-motion row and one row per pretraining.
    for row in ("zero-motion", "regression", "contrastive"):
        assert re.search(rf"\| {row} \| [0-9.]+ ± [0-9.]+ \| [0-9.]+ ± [0-9.]+ \| [0-9.]+ ± [0-9.]+ \|", report), row
    for row in ("model", "icp", "identity"):
        assert f"| {row} |" in report
    assert "No verdicts: this is the quick profile" in report
    for claim in CLAIMS:
        line = next(l for l in report.splitlines() if l.startswith(f"- **{claim}:"))
        assert re.search(r"\*\*[a-z_0-9]+: not judged\*\*", line), line
        # mean ± std, then each seed's value in brackets
        assert re.search(r"Ours \(mean ± std \[per seed\]\): .*\d\.\d{3,4} ± \d\.\d{3,4} \[\d\.\d{3,4}, \d\.\d{3,4}\]", line), line
    assert "## Training: stopping rules and steps run" in report and "fixed 2 steps" in report
    # the learned chain's targets: a row each, not judged in the quick profile, every seed's figures
    number = r"\d\.\d+"
    # (no ✓/✗ marks: the quick profile judges nothing)
    cells = {"flow_vs_zero_motion_ratio": rf"{number} × \(no gate {number} ×\); contrastive {number} vs regression {number}",
             "oracle_flow_boxes": rf"static {number} / moving {number}",
             "learned_boxes": rf"static {number} vs bar {number} / moving {number} vs bar {number}",
             "egomotion_vs_icp_ratio": rf"R {number} ×, t {number} ×",
             "occupancy": rf"occupied {number}, free {number}"}
    for target, cell in cells.items():
        assert re.search(rf"\| {target} \| [^|]+ \| – \| {cell} \| {cell} \|", report), target


def test_metrics_json_has_every_key(bench_run):
    out, _ = bench_run
    payload = json.loads((out / "metrics.json").read_text())
    metrics = payload["metrics"]
    assert set(METRIC_KEYS) <= set(metrics)
    assert metrics["seeds"] == [0, 1] and metrics["config"]["quick"] is True
    assert metrics["wall_time_s"] > 0 and metrics["total_stage_seconds"] > 0
    # every stage names the commit it ran at (the parent's and the seed workers' alike), when this is a checkout
    from services.training.job import git_commit
    commit = git_commit()
    assert set(metrics["stage_code"]) == set(metrics["stage_seconds"])
    assert all(code == [commit or "?"] for code in metrics["stage_code"].values()), metrics["stage_code"]
    assert [c["id"] for c in metrics["claims"]] == list(CLAIMS)
    for claim in metrics["claims"]:
        assert claim["holds"] is None and claim["verdict"] == "not judged" and claim["ours"] and claim["criterion"]
        assert set(claim["per_seed"]) == {"0", "1"}
    det = metrics["detection"]["contrastive/frozen"]
    assert set(det) == {"2", "all"} and set(det["2"]) == {"0.33", "0.5", "0.75"}
    for cell in (det["2"]["0.5"], metrics["flow"]["zero-motion"]["moving"], metrics["occupancy"]["contrastive, occupancy module, balanced threshold"]["acc_all"]):
        assert cell["n"] == 2 and 0.0 <= cell["mean"] and cell["std"] >= 0.0
    # The claim's occupancy module, then each pretraining's own head.
    assert list(metrics["occupancy"]) == ["contrastive, occupancy module, balanced threshold",
                                          "contrastive, occupancy module, threshold 0.5",
                                          "regression, pretraining head", "contrastive, pretraining head"]
    # the balanced threshold is one of the grid's, chosen on the validation records
    assert 0.05 <= metrics["occupancy"]["contrastive, occupancy module, balanced threshold"]["threshold"]["mean"] <= 0.95
    for arm in ("random", "regression", "contrastive"):
        for dim in ("2d", "3d"):
            p = [metrics["retrieval"][arm][dim][k]["mean"] for k in ("p@1", "p@5", "p@10")]
            assert 0.0 <= p[0] <= p[1] <= p[2] <= 1.0   # precision at K cannot fall as K grows
    # egomotion: the trained module's rows, the baselines, and the untrained module's rows (the control)
    assert {"model", "model, learned stages only", "icp", "identity", "untrained module",
            "untrained module, learned stages only"} <= set(metrics["egomotion"])
    for setting in ("static", "moving"):
        assert "2.5D Farneback" in metrics["moving"][setting]
        assert "contrastive, GT egomotion" in metrics["moving"][setting]
        assert "input volumes, egomotion module" in metrics["moving"][setting]
    # The arms' flow modules compare their features (the paper's protocol); the extra row compares volumes.
    assert {"contrastive", "regression", "input volumes"} <= set(metrics["flow"])
    for arm, inputs in (("contrastive", "features"), ("regression", "features"), ("volume", "volume")):
        bundle = json.loads((out / "work" / "seed0" / f"flow_{arm}" / "bundle" / "bundle.json").read_text())
        assert bundle["modules"]["flow"]["config"]["inputs"] == inputs
        # --task-options: the mapper option reaches every stage that builds a mapper, the flow_features
        # options only the arms' flow stages
        assert bundle["modules"]["mapper"]["config"]["full_res"] == 4
        flow_config = bundle["modules"]["flow"]["config"]
        if inputs == "features":
            assert (flow_config["refine_radius"], flow_config["refine_aggregate"]) == ([2, 1, 2], [1, 0, 1])
        else:   # the input-volume row is n3dmap's default flow: the task's own window
            assert (flow_config["refine_radius"], flow_config["refine_aggregate"]) == ([3, 1, 3], [1, 1, 1])
    assert metrics["config"]["task_options"] == TASK_OPTIONS
    for stage in ("pretrain_contrastive", "detector_contrastive_frozen_L2"):
        bundle = json.loads((out / "work" / "seed1" / stage / "bundle" / "bundle.json").read_text())
        assert bundle["modules"]["mapper"]["config"]["full_res"] == 4, stage
    pretrain = json.loads((out / "work" / "seed0" / "pretrain_regression" / "bundle" / "bundle.json").read_text())
    assert pretrain["provenance"]["coeff_match"] == 0.5
    assert "shift_positives" not in pretrain["provenance"]  # "pretrain_contrastive" reaches that arm only
    pretrain = json.loads((out / "work" / "seed0" / "pretrain_contrastive" / "bundle" / "bundle.json").read_text())
    assert pretrain["provenance"]["coeff_match"] == 0.5 and pretrain["provenance"]["shift_positives"] == 1
    # the report says which recipe it ran
    assert "- task_options: {'mapper': {'encoder_full_res': 4}" in (out / "report.md").read_text()
    # The quick plan's two label draws at 2 labels: draw 1 trains on records 2 and 3, the row is the draws' mean.
    train = ShardDataset(out / "work" / "data" / "train")
    for draw, first in ((0, 0), (1, 2)):
        stage = "detector_contrastive_finetuned_L2" + ("_draw1" if draw else "")
        labelled = ShardDataset(out / "work" / "seed0" / stage / "labelled_data")
        assert [labelled.key(i) for i in range(len(labelled))] == [train.key(first), train.key(first + 1)]
    row = metrics["per_seed"]["0"]["detection"]["contrastive/finetuned/2"]
    assert len(row["draws"]) == 2 and row["map"]["0.5"] == pytest.approx(sum(d["0.5"] for d in row["draws"]) / 2)
    assert "draws" not in metrics["per_seed"]["0"]["detection"]["contrastive/finetuned/all"]
    draws_table = (out / "report.md").read_text().split("by draw")[1].split("mAP at IoU")[0]
    assert "| contrastive − regression (frozen) |" in draws_table  # the difference the few-label claim reads
    assert "| contrastive − regression (fine-tuned) |" not in draws_table  # the quick plan has no regression/finetuned
    assert re.search(r"\| contrastive/finetuned \| [0-9.]+ ± [0-9.]+ \| [0-9.]+ ± [0-9.]+ \|",
                     (out / "report.md").read_text().split("by draw")[1])
    # Every stage left its timing, and the per-seed raw results are kept.
    assert all(s >= 0 for s in metrics["stage_seconds"].values())
    assert set(metrics["per_seed"]) == {"0", "1"}
    # Each training stage says how long it trained and why (the quick profile: a fixed 2 steps).
    pretrain = metrics["stopping"]["1"]["pretrain_contrastive"]
    assert pretrain["steps_run"] == 2 and pretrain["rule"]["kind"] == "fixed"


def test_rerun_skips_finished_stages(bench_run):
    out, first = bench_run
    journal = out / "work" / "stages.jsonl"
    before = len(journal.read_text().splitlines())
    second = _bench(out)
    ran = [l for l in second.stdout.splitlines() if l.startswith("[bench]") and l.endswith(": running")]
    skipped = [l for l in second.stdout.splitlines() if "skipped" in l]
    assert ran == [] and len(skipped) == len(json.loads((out / "metrics.json").read_text())["metrics"]["stage_seconds"])
    # The seed workers of the rerun (their output goes to their logs) skipped every stage too.
    appended = [json.loads(l) for l in journal.read_text().splitlines()[before:]]
    assert appended and {e["status"] for e in appended} == {"skipped"}
    assert (out / "report.md").is_file()
    # the processes that wrote the run have left no pid file behind (services.bench.running)
    assert not list((out / "work").rglob("*.pid"))


def test_status_of_a_finished_run_lists_every_stage_as_finished(bench_run):
    out, _ = bench_run
    proc = subprocess.run([sys.executable, "-m", "services.cli.main", "bench", "status", "--out", str(out), "--json"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    status = json.loads(proc.stdout)
    stages = json.loads((out / "metrics.json").read_text())["metrics"]["stage_seconds"]
    assert {r["name"] for r in status["stages"]} == set(stages)
    assert status["counts"] == {"finished": len(stages), "under way": 0, "to run": 0}


def test_thread_plan_is_printed_and_fits_the_cpus(bench_run):
    from services.threads import usable_cpus

    _, first = bench_run
    plans = re.findall(r"(\d+) process\(es\) × (\d+) torch thread\(s\) on (\d+) usable CPU", first.stdout)
    assert len(plans) == 2, first.stdout[:2000]          # sequential stages, then the seeds in parallel
    for processes, threads, cpus in plans:
        assert int(cpus) == usable_cpus() and int(processes) * int(threads) <= int(cpus)
    workers = re.findall(r"seed (\d): worker pid \d+", first.stdout)
    assert sorted(workers) == ["0", "1"]


def test_changed_plan_is_refused_unless_rerun_changed_redoes_only_what_it_touches(bench_run, tmp_path):
    out, _ = bench_run
    copy = tmp_path / "report"
    shutil.copytree(out, copy)
    options = {**TASK_OPTIONS, "flow_features": {"refine_radius": [1, 1, 1], "refine_aggregate": [1, 1, 1]}}
    refused = _bench(copy, options=options, check=False)
    assert refused.returncode == 2 and "Traceback" not in refused.stderr, refused.stderr[-2000:]
    assert "differs in ['task_options']" in refused.stderr and "--rerun-changed" in refused.stderr
    journal = copy / "work" / "stages.jsonl"
    before = len(journal.read_text().splitlines())
    rerun = _bench(copy, options=options, extra=("--rerun-changed",))
    assert "[bench] plan changed in ['task_options']" in rerun.stdout
    # Only the arms' flow stages and what reads them ran again, in both seeds (their workers' journal lines).
    appended = [json.loads(l) for l in journal.read_text().splitlines()[before:]]
    ran = {e["stage"] for e in appended if e["status"] == "ran"}
    assert ran == {f"seed{seed}/{stage}" for seed in (0, 1) for stage in (
        "flow_regression", "flow_contrastive", "eval/flow/regression", "eval/flow/contrastive", "eval/moving/all")}
    # and the report counts the stages the workers ran as this invocation's
    report = (copy / "report.md").read_text()
    assert f"Stages rerun by this invocation: {len(ran)} of " in report
    assert f"| seed1/flow_contrastive |" in report and re.search(r"\| seed1/flow_contrastive \| [\d.]+ \| yes \|", report)
    bundle = json.loads((copy / "work" / "seed0" / "flow_contrastive" / "bundle" / "bundle.json").read_text())
    assert bundle["modules"]["flow"]["config"]["refine_radius"] == [1, 1, 1]
    assert json.loads((copy / "work" / "plan.json").read_text())["task_options"] == options
    assert json.loads((copy / "metrics.json").read_text())["metrics"]["config"]["task_options"] == options


def test_redo_reruns_the_named_stages_and_what_reads_them_and_refuses_an_unknown_name(bench_run, tmp_path):
    out, _ = bench_run
    copy = tmp_path / "report"
    shutil.copytree(out, copy)
    journal = copy / "work" / "stages.jsonl"
    before = len(journal.read_text().splitlines())
    rerun = _bench(copy, extra=("--redo", "seed1/egomotion", "seed*/eval/occupancy/module_contrastive_balanced"))
    assert "[bench] --redo " in rerun.stdout
    appended = [json.loads(l) for l in journal.read_text().splitlines()[before:]]
    ran = {e["stage"] for e in appended if e["status"] == "ran"}
    assert ran == {"seed1/egomotion", "seed1/eval/egomotion/moving_camera", "seed1/eval/moving/all",
                   "seed0/eval/occupancy/module_contrastive_balanced",
                   "seed1/eval/occupancy/module_contrastive_balanced"}
    assert f"Stages rerun by this invocation: {len(ran)} of " in (copy / "report.md").read_text()
    bad = _bench(copy, extra=("--redo", "seed0/no_such_stage"), check=False)
    assert bad.returncode == 2 and "Traceback" not in bad.stderr, bad.stderr[-2000:]
    assert "--redo 'seed0/no_such_stage' matches no stage" in bad.stderr


def test_occupancy_and_egomotion_stages_export_their_weight_average(bench_run):
    from safetensors.torch import load_file

    from core.bundle import load_bundle
    from services.training.checkpoints import AVERAGE_FILE

    out, _ = bench_run
    for stage, module in (("occupancy_contrastive", "occupancy"), ("egomotion", "egomotion")):
        run = out / "work" / "seed0" / stage
        bundle = load_bundle(run / "selected")
        assert bundle.meta["provenance"]["ema_decay"] == 0.995
        checkpoint = sorted((run / "checkpoints").glob("checkpoint_*"))[-1]
        average = load_file(str(checkpoint / AVERAGE_FILE))
        name, value = next((k, v) for k, v in bundle.modules[module].state_dict().items() if v.is_floating_point())
        torch.testing.assert_close(value, average[f"{module}.{name}"])
    # the other stages keep none
    assert load_bundle(out / "work" / "seed0" / "pretrain_contrastive" / "selected").meta["provenance"]["ema_decay"] == 0.0


def test_a_seed_worker_stopped_by_a_signal_is_reported_as_resumable_and_the_rerun_finishes(bench_run, tmp_path):
    import os
    import signal

    out, _ = bench_run
    copy = tmp_path / "report"
    shutil.copytree(out, copy)
    proc, log, size = _rerun_seed1_egomotion_until_it_trains(copy)
    try:
        children = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text().split()
        pid = next(int(c) for c in children if "--seed\x001\x00" in Path(f"/proc/{c}/cmdline").read_text())
        # while it runs, its work dir cannot be carried away
        busy = subprocess.run([sys.executable, "-m", "services.cli.main", "bench", "carry", "save", "--out", str(copy),
                               "--to", str(tmp_path / "carry")], cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert busy.returncode == 2 and "is still being written by pid" in busy.stderr, busy.stderr[-2000:]
        assert f"pid {pid} (seed1/worker.pid)" in busy.stderr and "Traceback" not in busy.stderr
        os.kill(pid, signal.SIGTERM)
        stdout, stderr = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 2 and "Traceback" not in stderr, stderr[-2000:]
    assert "seed 1 (stopped by a signal: [bench] seed 1: stopped (" in stderr
    assert "rerun the same command to resume it" in stderr
    assert "[bench] seed 1: worker stopped by a signal (a rerun resumes it)" in stdout
    assert "Traceback" not in log.read_text()[size:]
    rerun = _bench(copy)  # plain: resumes what the stopped worker left unfinished
    assert "[bench] seed 1: worker done" in rerun.stdout and (copy / "report.md").is_file()
    assert (copy / "work" / "seed1" / "egomotion" / "bundle" / "bundle.json").is_file()


def test_a_carried_run_restored_elsewhere_continues_where_it_stopped(bench_run, tmp_path):
    """`bench carry save` on one work dir (seed 1's egomotion as if stopped part-way), `bench carry restore` into
    a new --out, then the same `bench paper` command: only the stopped stage runs, from its carried checkpoint
    (the same weights as the original run's), and the report's numbers are the original's."""
    from safetensors.torch import load_file

    out, _ = bench_run
    source = tmp_path / "report"
    shutil.copytree(out, source)
    stopped = source / "work" / "seed1" / "egomotion"
    for name in ("stopping.json", "stage.json"):
        (stopped / name).unlink()
    shutil.rmtree(stopped / "selected")

    def cli(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "services.cli.main", "bench", "carry", *args], cwd=ROOT,
                              capture_output=True, text=True, timeout=300)

    carry = tmp_path / "carry"
    saved = cli("save", "--out", str(source), "--to", str(carry))
    assert saved.returncode == 0, saved.stderr[-2000:]
    files = set(json.loads((carry / "carry.json").read_text())["files"])
    assert not any((f.startswith("data/") and not f.endswith("/stage.json")) or "/labelled_data/" in f or "/bundle/" in f
                   for f in files)
    assert "seed0/egomotion/stopping.json" in files and not any(f.startswith("seed0/egomotion/checkpoints/") for f in files)
    newest = sorted((stopped / "checkpoints").glob("checkpoint_*"))[-1].relative_to(source / "work").as_posix()
    assert {f for f in files if f.startswith("seed1/egomotion/checkpoints/")} == {
        f"{newest}/{p.name}" for p in (source / "work" / newest).iterdir()}

    restored = tmp_path / "restored"
    done = cli("restore", "--from", str(carry), "--out", str(restored))
    assert done.returncode == 0, done.stderr[-2000:]
    again = cli("restore", "--from", str(carry), "--out", str(restored))
    assert again.returncode == 2 and "already holds a benchmark" in again.stderr and "Traceback" not in again.stderr

    journal = restored / "work" / "stages.jsonl"
    before = len(journal.read_text().splitlines())
    worker_log = restored / "work" / "seed1" / "worker.log"
    log_size = worker_log.stat().st_size
    _bench(restored)
    appended = [json.loads(l) for l in journal.read_text().splitlines()[before:]]
    assert {e["stage"] for e in appended if e["status"] == "ran"} == {"seed1/egomotion"}
    # it trained no step: its carried checkpoint had reached the stage's last one, so it was exported as it is
    continued_log = worker_log.read_text()[log_size:]
    assert "[bench] seed1/egomotion: running" in continued_log
    assert not re.search(r"^step +\d+/", continued_log, flags=re.M), continued_log[-2000:]
    mine, theirs = (load_file(str(d / "work" / "seed1" / "egomotion" / "selected" / "weights.safetensors"))
                    for d in (restored, out))
    assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine)
    original = json.loads((out / "metrics.json").read_text())["metrics"]
    continued = json.loads((restored / "metrics.json").read_text())["metrics"]
    for key in ("detection", "retrieval", "flow", "moving", "occupancy", "egomotion", "claims", "per_seed"):
        assert continued[key] == original[key], key


def test_sigterm_to_the_bench_stops_its_workers_and_a_second_run_meanwhile_is_refused(bench_run, tmp_path):
    """SIGTERM to `bench paper` stops it as Ctrl-C does: exit 130 with one line, its seed workers stopped and
    waited for, no pid file left; while it ran, a second `bench paper` on the same --out was refused by name."""
    import os
    import signal

    out, _ = bench_run
    copy = tmp_path / "report"
    shutil.copytree(out, copy)
    proc, log, size = _rerun_seed1_egomotion_until_it_trains(copy)
    try:
        second = subprocess.run(_bench_cmd(copy), cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert second.returncode == 2 and "Traceback" not in second.stderr, second.stderr[-2000:]
        assert f"is being written by pid {proc.pid} (bench.pid)" in second.stderr
        os.kill(proc.pid, signal.SIGTERM)
        _, stderr = proc.communicate(timeout=180)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130 and stderr.strip().splitlines()[-1] == "n3dmap bench: interrupted", stderr[-2000:]
    assert "[bench] seed 1: stopped (" in log.read_text()[size:]
    assert not list((copy / "work").rglob("*.pid"))   # workers waited for, the parent's own file removed
