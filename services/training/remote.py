"""Ray Jobs: send a training command to a Ray cluster and manage it (submit/list/status/logs/stop).

`--address` is the cluster's dashboard (job server) address, e.g. `http://HEAD:8265` (a bare
`HOST:PORT` gets `http://`). The job runs the same `n3dmap train ...` command on the cluster, as
`python -m services.cli.main train ... --attach` so that it joins that cluster instead of starting its
own Ray. Code reaches the cluster one of two ways:

- working_dir (default when this code runs from a source checkout): the project root is uploaded
  as the job's runtime_env working_dir (without .git, .venv, caches, datasets and run dirs);
- none: nothing is uploaded; the cluster's image must have n3dmap installed (docker/ images do).

Paths in the command (--data, --run-dir, --init) are made absolute and must exist on the cluster
(a shared filesystem on multi-node clusters). Ray 2.60 clusters may require token auth: export
RAY_AUTH_MODE=token with the token in ~/.ray/auth_token (Ray's own clients read them).
"""

from __future__ import annotations

import asyncio
import shlex
import sys
import time
from pathlib import Path
from typing import TextIO

from core.errors import N3dmapError

# Never upload these. Ray reads them as gitignore patterns, where a bare name matches at any depth: "data" left
# out core/data/ (the code the job imports first), so the project's own folders of data and runs are anchored to
# the working dir's root with a leading "/". Ray also honours the project's .gitignore (out/, quickstart/, ...).
UPLOAD_EXCLUDES = [".git", ".venv", "venv", "**/__pycache__", "*.pyc", ".pytest_cache", "*.tar",
                   "*.safetensors", "/runs", "/data", "/out", "/quickstart", "/carry", "node_modules",
                   ".mypy_cache", ".ruff_cache"]
TERMINAL = ("SUCCEEDED", "FAILED", "STOPPED")


class RemoteError(N3dmapError):
    """The Ray job server is unreachable, or refused a request (unknown job id, bad address...)."""


def normalize_address(address: str) -> str:
    """`HOST:PORT` → `http://HOST:PORT`; `ray://` (Ray Client) is not the job server."""
    address = address.strip().rstrip("/")
    if not address:
        raise RemoteError("empty --address; give the Ray dashboard address, e.g. http://127.0.0.1:8265")
    if address.startswith("ray://"):
        raise RemoteError(f"--address {address}: Ray Jobs talks to the dashboard (http://HOST:8265), "
                          f"not the Ray Client port")
    if "://" not in address:
        address = "http://" + address
    return address


def _client(address: str):
    from ray.job_submission import JobSubmissionClient

    url = normalize_address(address)
    try:
        return JobSubmissionClient(url)
    except (ConnectionError, RuntimeError, ValueError) as e:
        raise RemoteError(f"cannot reach the Ray job server at {url}: {_first_line(e)}") from None


def _first_line(error: BaseException) -> str:
    lines = [line.strip() for line in str(error).splitlines() if line.strip()]
    return lines[0] if lines else type(error).__name__


def _call(what: str, fn, *args, **kwargs):
    try:
        return fn(*args, **kwargs)
    except RemoteError:
        raise
    except (ConnectionError, RuntimeError, ValueError, OSError) as e:
        raise RemoteError(f"{what}: {_first_line(e)}") from None


def train_entrypoint(argv: list[str]) -> str:
    """The shell command a job runs: `python -m services.cli.main <argv...>`."""
    return shlex.join(["python", "-m", "services.cli.main", *argv])


def submit(address: str, argv: list[str], *, working_dir: str | Path | None,
           excludes: list[str] | None = None, submission_id: str | None = None,
           env_vars: dict[str, str] | None = None) -> str:
    """Submit `n3dmap <argv>` as a Ray job; returns the job (submission) id."""
    client = _client(address)
    runtime_env: dict = {}
    if working_dir is not None:
        runtime_env["working_dir"] = str(working_dir)
        runtime_env["excludes"] = list(UPLOAD_EXCLUDES) + list(excludes or [])
    if env_vars:
        runtime_env["env_vars"] = dict(env_vars)
    return _call("submitting the job", client.submit_job, entrypoint=train_entrypoint(argv),
                 runtime_env=runtime_env or None, submission_id=submission_id)


def list_jobs(address: str) -> list[dict]:
    """All jobs the cluster knows, oldest first: id, status, entrypoint, start/end times (ms)."""
    client = _client(address)
    jobs = _call("listing jobs", client.list_jobs)
    rows = [{"id": j.submission_id or j.job_id, "status": str(j.status.value if hasattr(j.status, "value")
                                                                else j.status),
             "entrypoint": j.entrypoint, "start_time": j.start_time, "end_time": j.end_time,
             "message": j.message} for j in jobs]
    return sorted(rows, key=lambda r: r["start_time"] or 0)


def job_info(address: str, job_id: str) -> dict:
    client = _client(address)
    info = _call(f"job {job_id}", client.get_job_info, job_id)
    status = info.status.value if hasattr(info.status, "value") else str(info.status)
    return {"id": job_id, "status": status, "entrypoint": info.entrypoint, "message": info.message,
            "start_time": info.start_time, "end_time": info.end_time}


def job_logs(address: str, job_id: str) -> str:
    client = _client(address)
    return _call(f"logs of job {job_id}", client.get_job_logs, job_id)


def follow_logs(address: str, job_id: str, out: TextIO | None = None) -> str:
    """Stream a job's logs to `out` until it ends; returns its final status."""
    out = out if out is not None else sys.stdout
    client = _client(address)

    async def tail() -> None:
        async for chunk in client.tail_job_logs(job_id):
            out.write(chunk)
            out.flush()

    _call(f"logs of job {job_id}", asyncio.run, tail())
    return wait_for_job(address, job_id, timeout_s=30.0)


def stop_job(address: str, job_id: str) -> bool:
    """Ask the cluster to stop a job; False if it had already ended."""
    client = _client(address)
    return bool(_call(f"stopping job {job_id}", client.stop_job, job_id))


def wait_for_job(address: str, job_id: str, *, timeout_s: float, poll_s: float = 1.0) -> str:
    """Poll until the job reaches SUCCEEDED / FAILED / STOPPED; returns that status."""
    deadline = time.monotonic() + timeout_s
    while True:
        status = job_info(address, job_id)["status"]
        if status in TERMINAL:
            return status
        if time.monotonic() > deadline:
            raise RemoteError(f"job {job_id} still {status} after {timeout_s:.0f} s")
        time.sleep(poll_s)
