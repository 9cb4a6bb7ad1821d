"""CLI errors of `n3dmap train` / `jobs` / `bundle`: one line on stderr, exit 2; argv forwarding."""

import dataclasses

import pytest

from services.cli.main import build_parser, main


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_missing_data_dir_is_one_line_exit_2(tmp_path, capsys):
    rc = main(["train", "pretrain", "--data", str(tmp_path / "nope"), "--run-dir", str(tmp_path / "r"),
               "--workers", "0"])
    assert rc == 2
    assert _one_error_line(capsys) == f"n3dmap train: error: --data {tmp_path / 'nope'}: no such dataset directory"


def test_data_dir_without_manifest_is_one_line_exit_2(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    rc = main(["train", "pretrain", "--data", str(tmp_path / "empty"), "--run-dir", str(tmp_path / "r"),
               "--workers", "0"])
    assert rc == 2
    assert "has no manifest.json" in _one_error_line(capsys)


@pytest.mark.parametrize("flag, value, message", [
    ("--workers", "-1", "--workers must be >= 0"),
    ("--steps", "0", "--steps must be >= 1"),
    ("--preset", "huge", "unknown preset 'huge'"),
    ("--ema-decay", "1.0", "--ema-decay must lie in [0, 1) (0: off), got 1.0"),
])
def test_bad_options_are_one_line_exit_2(tmp_path, capsys, flag, value, message):
    data = tmp_path / "data"
    data.mkdir()
    (data / "manifest.json").write_text("{}")
    rc = main(["train", "pretrain", "--data", str(data), "--run-dir", str(tmp_path / "r"), "--workers", "0",
               flag, value])
    assert rc == 2
    assert message in _one_error_line(capsys)


def test_jobs_without_address_is_one_line_exit_2(capsys, monkeypatch):
    monkeypatch.delenv("RAY_ADDRESS", raising=False)
    assert main(["jobs", "list"]) == 2
    assert "no --address given" in _one_error_line(capsys)


def test_jobs_with_unreachable_address_is_one_line_exit_2(capsys):
    import socket

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    assert main(["jobs", "status", "raysubmit_x", "--address", f"127.0.0.1:{port}"]) == 2
    assert f"http://127.0.0.1:{port}" in _one_error_line(capsys)


def test_bundle_info_of_a_non_bundle_is_one_line_exit_2(tmp_path, capsys):
    assert main(["bundle", "info", str(tmp_path)]) == 2
    assert "not a bundle" in _one_error_line(capsys)


def test_forwarded_argv_drops_submission_flags_and_makes_paths_absolute(tmp_path, monkeypatch):
    from services.cli.train import forwarded_argv

    monkeypatch.chdir(tmp_path)
    given = ["train", "pretrain", "--data", "d", "--run-dir", "r", "--objective", "regression", "--steps", "7",
             "--freeze-features", "--address", "http://h:8265", "--follow", "--workers", "2", "--precision", "bf16"]
    args = build_parser(given).parse_args(given)
    argv = forwarded_argv("pretrain", args)
    assert argv[:2] == ["train", "pretrain"] and argv[-1] == "--attach"
    assert "--address" not in argv and "--follow" not in argv
    assert "--freeze-features" in argv
    assert str(tmp_path / "d") in argv and str(tmp_path / "r") in argv
    assert "--steps" in argv and argv[argv.index("--steps") + 1] == "7"
    assert argv[argv.index("--objective") + 1] == "regression"
    # Parsing the forwarded command gives the same options back.
    again = build_parser(argv).parse_args(argv)
    for name in ("steps", "objective", "freeze_features", "workers", "precision"):
        assert getattr(again, name) == getattr(args, name)
    assert again.attach and again.address is None


def test_flow_over_features_without_init_is_one_line_exit_2(tmp_path, capsys):
    rc = main(["train", "flow", "--data", str(tmp_path), "--run-dir", str(tmp_path / "r"), "--inputs", "features"])
    assert rc == 2
    line = _one_error_line(capsys)
    assert "--inputs features" in line and "--init BUNDLE" in line
    assert not (tmp_path / "r").exists()  # refused before anything was written


def test_match_weight_reaches_the_task_options_and_a_negative_one_is_refused(tmp_path, capsys, monkeypatch):
    import services.cli.train_tasks.pretrain as pretrain_cli

    seen = {}
    monkeypatch.setattr(pretrain_cli, "run_train", lambda task, args, options: seen.update(options) or 0)
    base = ["train", "pretrain", "--data", str(tmp_path), "--run-dir", str(tmp_path / "r")]
    assert main(base + ["--match-weight", "0.5"]) == 0
    assert seen == {"objective": "contrastive", "coeff_match": 0.5}
    seen.clear()
    assert main(base) == 0
    assert seen == {"objective": "contrastive"}  # off: the paper's objective, nothing extra recorded
    seen.clear()
    assert main(base + ["--encoder-full-res", "16", "--occupancy-weight", "3"]) == 0
    assert seen == {"objective": "contrastive", "encoder_full_res": 16, "coeff_occ": 3.0}
    seen.clear()
    assert main(base + ["--local-negatives", "1", "--local-negative-radius", "3"]) == 0
    assert seen == {"objective": "contrastive", "coeff_local_negatives": 1.0, "local_negative_radius": 3}
    seen.clear()
    assert main(base + ["--shift-positives", "3"]) == 0
    assert seen == {"objective": "contrastive", "shift_positives": 3}
    with pytest.raises(SystemExit) as stop:
        main(base + ["--match-weight", "-1"])
    assert stop.value.code == 2 and "--match-weight" in capsys.readouterr().err


def test_flow_radius_reaches_the_task_options(tmp_path, monkeypatch):
    import services.cli.train_tasks.flow as flow_cli

    seen = {}
    monkeypatch.setattr(flow_cli, "run_train", lambda task, args, options: seen.update(options) or 0)
    base = ["train", "flow", "--data", str(tmp_path), "--run-dir", str(tmp_path / "r")]
    assert main(base + ["--radius", "2", "1", "2"]) == 0
    assert seen["radius"] == [2, 1, 2]
    seen.clear()
    assert main(base) == 0
    assert "radius" not in seen  # the module's default
    seen.clear()
    assert main(base + ["--radius", "3", "1", "3", "--refine-radius", "1", "1", "1", "--cost-channels", "16"]) == 0
    assert seen["radius"] == [3, 1, 3] and seen["refine_radius"] == [1, 1, 1] and seen["cost_channels"] == 16
    assert "refine_aggregate" not in seen
    seen.clear()
    assert main(base + ["--refine-aggregate", "1", "0", "1"]) == 0
    assert seen["refine_aggregate"] == [1, 0, 1]


class _Captured(Exception):
    """Raised by the stand-in for run_training: the config a command would train with, without training."""


@pytest.mark.parametrize("task, extra", [
    ("detector", []), ("detector", ["--finetune"]), ("detector", ["--freeze-features"]),
    ("egomotion", []), ("egomotion", ["--refine"]), ("egomotion", ["--no-refine", "--no-augment"]),
    ("pretrain", ["--objective", "regression", "--freeze-features", "--steps", "5"]),
    ("occupancy", []), ("flow", []),
])
def test_a_submitted_job_trains_as_the_command_would_here(tmp_path, monkeypatch, task, extra):
    """`train TASK ... --address A` submits a command (forwarded_argv, after the task's own handler ran) that, run on
    the cluster, configures the same training as the command run here: booleans travel as bare flags (`--refine`,
    `--no-refine`, not `--no-refine True`), and a flag a handler filled in (the detector's freeze_features) does
    not travel beside the one that set it (`--freeze-features --finetune` is refused)."""
    import services.training.job as job
    import services.training.remote as remote

    data, run = tmp_path / "data", tmp_path / "run"
    data.mkdir()
    base = ["train", task, "--data", str(data), "--run-dir", str(run), "--preset", "tiny", *extra]
    configs, submitted = [], []

    def capture(config):
        configs.append(config)
        raise _Captured

    monkeypatch.setattr(job, "run_training", capture)
    monkeypatch.setattr(remote, "submit", lambda address, argv, **kw: submitted.append(argv) or "raysubmit_1")
    with pytest.raises(_Captured):
        main(base)                                          # here
    assert main([*base, "--address", "http://h:8265"]) == 0
    (argv,) = submitted
    assert argv[-1] == "--attach" and "True" not in argv and "False" not in argv, argv
    with pytest.raises(_Captured):
        main(argv)                                          # what the cluster runs
    here, there = configs
    assert there.attach and not here.attach
    assert dataclasses.replace(there, attach=False) == here, argv
