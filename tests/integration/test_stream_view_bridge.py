"""The quick start's stream step with the viz extra (services.quickstart.stream): a real bridge over an
untrained stream bundle, the simulated camera, the listener and `n3dmap stream view --save`, as separate
processes on loopback zenoh. The recording holds one detections entry per frame the bridge processed
(its final accounting), one frame entry per frame published, and at least one box somewhere (the
untrained correlators find moving cars on the synthetic stream: tests/stream_bundles.py).
"""

from __future__ import annotations

import re

import numpy as np
import pytest

pytest.importorskip("rerun")

from services import quickstart  # noqa: E402
from services.viz import rerun_paths as paths  # noqa: E402
from tests.rrd_reading import Recording, array, rerun_cli  # noqa: E402
from tests.stream_bundles import untrained_stream_bundle  # noqa: E402

pytestmark = [pytest.mark.integration, pytest.mark.slow]


def test_quickstart_stream_step_records_every_processed_frame(tmp_path, capfd, monkeypatch):
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    bundle = untrained_stream_bundle("tiny", tmp_path / "bundle", provenance={"test": "stream view"})
    recording = quickstart.stream(bundle, tmp_path)
    out = capfd.readouterr().out
    assert recording == tmp_path / "stream.rrd" and recording.is_file(), out
    accounting = re.search(r"bridge accounting for cam0: received (\d+), processed (\d+).*scene_starts (\d+)", out)
    logged = re.search(r"viewer: logged (\d+) frames .*?, (\d+) detection messages, (\d+) egomotion messages", out)
    assert accounting and logged, out
    received, processed, scene_starts = map(int, accounting.groups())
    frames, detections, egomotion = map(int, logged.groups())
    # the camera's 16 frames are two 8-frame episodes: frames 0 and 8 start a scene and pair with nothing
    # (either dropped behind, the frame processed instead starts the scene, bridge.py; one only when every
    # frame from 0 to 8 was dropped)
    assert 1 <= scene_starts <= 2 and received == 16 and processed >= 2 and detections == processed, out
    assert egomotion == processed - scene_starts, out
    assert frames == 16, out  # the view saw every frame the camera published

    assert rerun_cli("rrd", "verify", str(recording)).returncode == 0
    rec = Recording(recording)
    entries = rec.at(paths.DETECTIONS, "Boxes3D:centers", paths.FRAME)
    assert len(entries) == processed
    assert len(rec.at(paths.STREAM_IMAGE, "Image:buffer", paths.FRAME)) == 16
    assert sum(len(array(v, 3)) for v in entries.values()) > 0, "the bridge published no box at all"
    assert len(rec.at(paths.TRAJECTORY_EGO, "LineStrips3D:strips", paths.FRAME)) == processed - scene_starts
    assert np.isfinite(array(rec.at(paths.TRAJECTORY, "LineStrips3D:strips", paths.FRAME)[15][0], 3)).all()
