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
