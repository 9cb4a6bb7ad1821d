"""The stage journal (WORK/stages.jsonl): the stages run after an offset, as the report counts them when
seed workers ran them in other processes."""

import json

from services.bench.stages import JOURNAL, StageRunner, journal_size, stages_ran_since


def _done(stage_dir):
    (stage_dir / "done").write_text("1")


def test_stages_ran_since_lists_only_what_ran_after_the_offset(tmp_path):
    work = tmp_path / "work"
    assert journal_size(work) == 0 and stages_ran_since(work, 0) == []
    StageRunner(work, log=lambda line: None).run("a", "done", _done)
    start = journal_size(work)
    assert start > 0
    # another process (a seed worker) journals: "a" again (skipped), then runs "b" and "c"
    worker = StageRunner(work, log=lambda line: None)
    for name in ("a", "b", "c"):
        worker.run(name, "done", _done)
    with open(work / JOURNAL, "a") as f:
        f.write('{"stage": "d", "seconds": 1.0, "sta')   # cut off by a killed worker
    assert stages_ran_since(work, start) == ["b", "c"]
    assert stages_ran_since(work, 0) == ["a", "b", "c"]
    lines = (work / JOURNAL).read_text().splitlines()
    assert [json.loads(l)["status"] for l in lines[:4]] == ["ran", "skipped", "ran", "ran"]


def test_a_stage_stopped_part_way_reports_the_time_of_all_its_attempts(tmp_path, monkeypatch):
    import time
    from types import SimpleNamespace

    import pytest

    import services.bench.stages as stages

    clock = iter([100.0, 130.0, 200.0, 205.0])  # attempt 1 runs 30 s and is stopped; attempt 2 runs 5 s
    monkeypatch.setattr(stages, "time", SimpleNamespace(monotonic=lambda: next(clock), strftime=time.strftime))
    lines: list[str] = []
    work = tmp_path / "work"

    def stopped(stage_dir):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        StageRunner(work, log=lines.append).run("a", "done", stopped)
    assert json.loads((work / "a" / stages.PARTIAL).read_text())["seconds"] == 30.0
    assert not (work / "a" / "stage.json").exists() and stages_ran_since(work, 0) == []
    runner = StageRunner(work, log=lines.append)
    runner.run("a", "done", _done)
    assert lines[-2:] == ["[bench] a: running (30.0 s in earlier attempts)", "[bench] a: 35.0 s"]
    assert json.loads((work / "a" / "stage.json").read_text())["seconds"] == runner.seconds["a"] == 35.0
    assert not (work / "a" / stages.PARTIAL).exists()
    assert [json.loads(l)["seconds"] for l in (work / JOURNAL).read_text().splitlines()] == [35.0]


def test_a_stage_records_the_commit_of_each_of_its_attempts(tmp_path):
    import pytest

    from services.training.job import git_commit

    work = tmp_path / "work"

    def stopped(stage_dir):
        raise KeyboardInterrupt

    first = StageRunner(work, log=lambda line: None)
    assert first.commit == git_commit()   # the checkout's HEAD (None outside a git checkout)
    first.commit = "a" * 40               # the first attempt ran at one commit …
    with pytest.raises(KeyboardInterrupt):
        first.run("s", "done", stopped)
    second = StageRunner(work, log=lambda line: None)
    second.commit = "b" * 40              # … and its resume at another
    second.run("s", "done", _done)
    assert json.loads((work / "s" / "stage.json").read_text())["code"] == ["a" * 40, "b" * 40] == second.code["s"]
    assert [json.loads(l)["code"] for l in (work / JOURNAL).read_text().splitlines()] == ["b" * 40]
    third = StageRunner(work, log=lambda line: None)
    third.run("s", "done", _done)         # skipped: reads the commits back for the report
    assert third.code["s"] == ["a" * 40, "b" * 40]
    (work / "old").mkdir()
    (work / "old" / "done").write_text("1")
    (work / "old" / "stage.json").write_text('{"stage": "old", "seconds": 2.0}')   # written before commits were kept
    third.run("old", "done", _done)
    assert third.code["old"] == ["?"]
    # a stage stopped before commits were recorded and resumed after: its earlier attempts are marked unknown
    (work / "resumed").mkdir()
    (work / "resumed" / "stage.partial.json").write_text('{"stage": "resumed", "seconds": 5.0}')
    third.run("resumed", "done", _done)
    assert third.code["resumed"] == (["?", third.commit] if third.commit else ["?"])


def test_an_attempt_killed_outright_still_names_its_commit(tmp_path):
    """A process killed outright (SIGKILL, a lost machine) writes nothing when it dies: the attempt's commit is on
    disk before the stage runs, so the stage's resume lists it; without a git checkout it is '?'."""
    work = tmp_path / "work"
    seen = {}

    def killed(stage_dir):   # what a later process finds if this one dies here
        seen.update(json.loads((stage_dir / "stage.partial.json").read_text()))

    runner = StageRunner(work, log=lambda line: None)
    runner.commit = "c" * 40
    try:
        runner.run("s", "done", killed)
    except RuntimeError:   # finished without its marker, as a killed stage would leave it
        pass
    assert seen["code"] == ["c" * 40]
    resumed = StageRunner(work, log=lambda line: None)
    resumed.commit = None                  # e.g. run from an unpacked copy, not a git checkout
    resumed.run("s", "done", _done)
    assert resumed.code["s"] == ["c" * 40, "?"]


def test_a_marker_that_does_not_parse_is_refused_naming_the_redo(tmp_path):
    """A marker left empty (a crash between a rename and the disk) said "finished" of a stage with nothing in it,
    and what read the stage then failed with a traceback; now the stage is refused by name, with the fix."""
    import pytest

    from services.bench.stages import StageError

    work = tmp_path / "work"
    StageRunner(work, log=lambda line: None).run("seed0/a", "done", _done)
    (work / "seed0" / "a" / "done").write_text("")
    ran = []
    with pytest.raises(StageError, match=r"stage seed0/a: its marker .*done is not readable JSON.*--redo seed0/a"):
        StageRunner(work, log=lambda line: None).run("seed0/a", "done", lambda d: ran.append(d))
    assert ran == []


def test_a_stage_stopped_between_its_marker_and_its_record_is_recorded_from_its_attempts(tmp_path):
    """A signal after the marker but before stage.json left the stage done with no time (NaN in every later
    report): the next run writes stage.json from the attempts' record."""
    from services.bench.stages import PARTIAL

    work = tmp_path / "work"
    stage = work / "seed0" / "a"

    def marker_then_stop(stage_dir):
        _done(stage_dir)
        raise KeyboardInterrupt   # the signal lands after the marker is written

    runner = StageRunner(work, log=lambda line: None)
    runner.commit = "c" * 40
    try:
        runner.run("seed0/a", "done", marker_then_stop)
    except KeyboardInterrupt:
        pass
    assert (stage / "done").exists() and not (stage / "stage.json").exists() and (stage / PARTIAL).exists()
    later = StageRunner(work, log=lambda line: None)
    later.run("seed0/a", "done", _done)
    record = json.loads((stage / "stage.json").read_text())
    assert record["seconds"] >= 0 and record["code"] == ["c" * 40] and not (stage / PARTIAL).exists()
    assert later.seconds["seed0/a"] == record["seconds"]
