"""What `n3dmap train --address ... --working-dir auto` uploads: walked with Ray's own traversal and pattern
matching (ray._private.runtime_env.packaging, the functions its upload zips with), so the test fails when a
pattern of UPLOAD_EXCLUDES means something else to Ray than to us."""

from __future__ import annotations

from pathlib import Path

from ray._private.runtime_env import packaging

from services.training.remote import UPLOAD_EXCLUDES

ROOT = Path(__file__).resolve().parents[3]


def uploaded(root: Path) -> set[str]:
    files: set[str] = set()
    packaging._dir_travel(root, [packaging._get_excludes(root, UPLOAD_EXCLUDES)],
                          lambda p: files.add(p.relative_to(root).as_posix()) if p.is_file() else None,
                          include_gitignore=True)
    return files


def test_every_package_the_job_imports_is_uploaded_and_the_project_data_is_not(tmp_path):
    # a copy of the layout that matters: the code's own data/ and runs/ packages, and the project's data folders
    for path in ("core/data/shards/manifest.py", "core/data/__init__.py", "services/training/runs/x.py",
                 "core/data/record.py", "data/train/shard-00000.tar", "data/train/manifest.json",
                 "runs/pretrain/state.json", "out/bench/report.md", "carry/x/work/plan.json",
                 "core/models/w.safetensors", "core/__pycache__/m.cpython-311.pyc"):
        (tmp_path / path).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / path).write_text("x")
    files = uploaded(tmp_path)
    assert {"core/data/shards/manifest.py", "core/data/__init__.py", "core/data/record.py",
            "services/training/runs/x.py"} <= files
    assert not any(f.split("/")[0] in ("data", "runs", "out", "carry") for f in files), files
    assert not any(f.endswith((".safetensors", ".pyc")) for f in files), files


def test_the_checkout_uploads_its_data_package():
    files = uploaded(ROOT)
    modules = {p.relative_to(ROOT).as_posix() for p in (ROOT / "core" / "data").rglob("*.py")
               if "__pycache__" not in p.parts}
    assert modules and modules <= files, sorted(modules - files)
    assert "services/cli/main.py" in files and "core/data/shards/manifest.py" in files
