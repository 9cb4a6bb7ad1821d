"""Ray Jobs: `n3dmap train ... --address` against a real `ray start --head` this test owns.

The job runs the same `n3dmap train pretrain` command on the cluster (code uploaded as the job's
working_dir), joins that cluster, trains, and exports the bundle; `n3dmap jobs` sees and reads it.
"""

import pytest

from services.cli.main import main
from tests.integration.ray_head import RayHead

pytestmark = [pytest.mark.integration, pytest.mark.slow]


@pytest.fixture(scope="module")
def ray_head():
    head = RayHead.start(num_cpus=3)
    try:
        yield head
    finally:
        head.stop()


def test_submitted_job_trains_and_jobs_cli_reports_it(ray_head, tiny_train_data, tmp_path, capsys):
    from core.bundle import load_bundle

    run = tmp_path / "run"
    rc = main(["train", "pretrain", "--objective", "regression", "--data", str(tiny_train_data),
               "--run-dir", str(run), "--workers", "1", "--steps", "2", "--batch-size", "1",
               "--checkpoint-every", "2", "--log-every", "1", "--object-store-mb", "100",
               "--address", ray_head.address, "--follow"])
    out = capsys.readouterr().out
    job_id = out.splitlines()[0].strip()
    assert rc == 0, out[-4000:]
    assert job_id.startswith("raysubmit_")
    assert "step 2/2 (100%)" in out and f"job {job_id}: SUCCEEDED" in out
    bundle = load_bundle(run / "bundle")
    assert bundle.meta["provenance"]["workers"] == 1 and bundle.meta["provenance"]["steps"] == 2

    assert main(["jobs", "list", "--address", ray_head.address]) == 0
    listed = [line for line in capsys.readouterr().out.splitlines() if line.startswith(job_id)]
    assert len(listed) == 1 and "SUCCEEDED" in listed[0] and "--attach" in listed[0]

    assert main(["jobs", "status", job_id, "--address", ray_head.address]) == 0
    assert capsys.readouterr().out.strip().startswith(f"{job_id}: SUCCEEDED")

    assert main(["jobs", "logs", job_id, "--address", ray_head.address]) == 0
    assert "step 2/2 (100%)" in capsys.readouterr().out

    assert main(["jobs", "stop", job_id, "--address", ray_head.address]) == 0
    assert capsys.readouterr().out.strip() == f"job {job_id}: already finished"

    assert main(["jobs", "status", "raysubmit_nope", "--address", ray_head.address]) == 2
    assert "raysubmit_nope" in capsys.readouterr().err
