"""Carry a running `n3dmap bench paper` work directory across machine resets, lean.

Sessions here start from a fresh clone (ignored files such as out/ are gone), while the small report takes
longer than one session. `pack` copies what a rerun needs to continue into .bench-carry/<name>/ (tracked):
plan, stage logs, every finished stage's marker/timing/stopping record and evaluation, the selected weights
that later stages still read (detector weights only until their evaluation exists), and for an unfinished
training stage its partial stopping record, best-so-far bundle and newest checkpoint. Datasets are not
packed: the data stages regenerate them bit-for-bit (checked: same sha256 of the shards).
`unpack` copies it back. Temporary: removed when docs/reports/bench-paper-small/ is regenerated.

    python .bench-carry/carry.py pack   out/bench-small
    python .bench-carry/carry.py unpack out/bench-small
"""
import shutil
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _keep(work: Path) -> list[Path]:
    keep = [p for p in (work / "plan.json", work / "stages.jsonl") if p.exists()]
    for seed_dir in sorted(work.glob("seed*")):
        keep += [seed_dir / "worker.log"] if (seed_dir / "worker.log").exists() else []
        keep += sorted(seed_dir.glob("eval/**/metrics.json")) + sorted(seed_dir.glob("eval/**/stage.json"))
        for run in sorted(p for p in seed_dir.iterdir() if p.is_dir() and p.name != "eval"):
            keep += [p for p in run.glob("*.json*") if p.is_file()]     # stopping, stage, metrics.jsonl
            finished = (run / "stopping.json").exists()
            if run.name.startswith("detector_"):
                name = run.name[len("detector_"):]
                evaluated = (seed_dir / "eval" / "detection" / name / "metrics.json").exists()
                if finished and evaluated:
                    continue
            keep += [p for p in (run / "selected").glob("*") if p.is_file()]
            if not finished:
                checkpoints = sorted((run / "checkpoints").glob("checkpoint_*"))
                if checkpoints:
                    keep += [p for p in checkpoints[-1].glob("*") if p.is_file()]
    return keep


def pack(out: Path) -> None:
    work, dest = out / "work", HERE / out.name / "work"
    if dest.exists():
        shutil.rmtree(dest)
    total = 0
    for path in _keep(work):
        target = dest / path.relative_to(work)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, target)
        total += path.stat().st_size
    print(f"packed {total / 1e6:.1f} MB into {dest}")


def unpack(out: Path) -> None:
    src = HERE / out.name / "work"
    shutil.copytree(src, out / "work", dirs_exist_ok=True)
    print(f"unpacked {src} into {out / 'work'}")


if __name__ == "__main__":
    {"pack": pack, "unpack": unpack}[sys.argv[1]](Path(sys.argv[2]))
