"""`n3dmap jobs list|status|logs|stop --address ADDR`: manage training jobs submitted to a Ray cluster.

ADDR is the cluster's job server (dashboard), e.g. http://HEAD:8265; it defaults to $RAY_ADDRESS.
"""

from __future__ import annotations

import argparse
import json
import os
import time



def _address(args: argparse.Namespace) -> str:
    address = args.address or os.environ.get("RAY_ADDRESS")
    if not address:
        from services.training.remote import RemoteError

        raise RemoteError("no --address given and RAY_ADDRESS is not set (e.g. --address http://HEAD:8265)")
    return address


def _when(ms: int | None) -> str:
    return time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(ms / 1000)) if ms else "-"


def _list(args: argparse.Namespace) -> int:
    from services.training import remote

    jobs = remote.list_jobs(_address(args))
    if args.json:
        print(json.dumps(jobs, indent=1))
        return 0
    if not jobs:
        print("no jobs")
        return 0
    width = max(len(j["id"]) for j in jobs)
    for j in jobs:
        print(f"{j['id']:<{width}}  {j['status']:<9}  {_when(j['start_time'])}  {j['entrypoint']}")
    return 0


def _status(args: argparse.Namespace) -> int:
    from services.training import remote

    info = remote.job_info(_address(args), args.job_id)
    if args.json:
        print(json.dumps(info, indent=1))
    else:
        print(f"{info['id']}: {info['status']}" + (f" ({info['message']})" if info["message"] else ""))
    return 0


def _logs(args: argparse.Namespace) -> int:
    from services.training import remote

    address = _address(args)
    if args.follow:
        status = remote.follow_logs(address, args.job_id)
        print(f"job {args.job_id}: {status}")
        return 0 if status == "SUCCEEDED" else 1
    print(remote.job_logs(address, args.job_id), end="")
    return 0


def _stop(args: argparse.Namespace) -> int:
    from services.training import remote

    stopped = remote.stop_job(_address(args), args.job_id)
    print(f"job {args.job_id}: " + ("stop requested" if stopped else "already finished"))
    return 0


def register(subparsers) -> None:
    jobs = subparsers.add_parser("jobs", help="list / inspect / stop training jobs on a Ray cluster",
                                 description=__doc__.splitlines()[0])
    actions = jobs.add_subparsers(dest="action", metavar="ACTION", required=True)

    def add(name: str, help: str, func, *, job_id: bool) -> argparse.ArgumentParser:
        p = actions.add_parser(name, help=help)
        if job_id:
            p.add_argument("job_id", metavar="ID", help="job (submission) id printed by `n3dmap train --address`")
        p.add_argument("--address", default=None, help="Ray job server, e.g. http://HEAD:8265 (default: $RAY_ADDRESS)")
        p.set_defaults(func=func)
        return p

    add("list", "list the cluster's jobs", _list, job_id=False).add_argument(
        "--json", action="store_true", help="print JSON")
    add("status", "show a job's status", _status, job_id=True).add_argument(
        "--json", action="store_true", help="print JSON")
    add("logs", "print a job's logs", _logs, job_id=True).add_argument(
        "--follow", action="store_true", help="stream the logs until the job ends")
    add("stop", "stop a running job", _stop, job_id=True)
