"""README "3D viewer (Rerun)": every `n3dmap` command it shows parses with the real CLI (options spelled
in full), every entity path and timeline it names is the one the recorders use (services.viz.rerun_paths),
and the screenshot it shows exists and is small."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

from services.viz import rerun_paths as paths
from tests.unit.deploy import manifests as m

ROOT = Path(__file__).resolve().parents[3]
START, END = "### 3D viewer (Rerun)", "## Running on a cluster"


def section() -> str:
    text = (ROOT / "README.md").read_text()
    assert START in text and END in text
    return text.split(START, 1)[1].split(END, 1)[0]


def test_every_command_parses():
    blocks = re.findall(r"```bash\n(.*?)```", section(), flags=re.S)
    commands = [re.split(r"\s+#\s", line, maxsplit=1)[0].strip() for block in blocks for line in block.splitlines()]
    commands = [c for c in commands if c.startswith("n3dmap ")]
    assert len(commands) >= 8
    for command in commands:
        argv = [a for a in shlex.split(command)[1:] if a not in ("[--points]",)]
        m.parse_n3dmap(argv, f"README `{command}`")


def test_named_entity_paths_and_timelines_are_the_recorders():
    text = section()
    named = {getattr(paths, n) for n in dir(paths) if n.isupper() and isinstance(getattr(paths, n), str)}
    named -= {paths.STREAM_EYE}  # an implementation detail of the default layout
    for value in named:
        assert f"`{value}" in text or f"{value}`" in text, f"README's Rerun section never names {value!r}"
    for camera in ("world/cam<v>", "ref/cam<v>"):
        assert camera in text and paths.camera(0) == "world/cam0" and paths.camera(0, paths.REF) == "ref/cam0"


def test_screenshot_is_there_and_small():
    shot = ROOT / "docs" / "images" / "rerun_quickstart.png"
    assert "docs/images/rerun_quickstart.png" in section()
    assert shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and shot.stat().st_size < 500_000
