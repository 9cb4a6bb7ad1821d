"""Render synthetic records in worker processes, yielding them in record order.

Used by `n3dmap data generate --jobs N` and by tests/benchmarks/bench_render.py --processes N.

Why processes of one torch thread each and not torch's intra-op threads: a record is an independent
unit of work, so N processes scale with no synchronisation, whereas every parallel torch op is an
OpenMP region whose barrier waits for all of its threads. On a machine busier than its core count
(shared CI, other jobs) a descheduled OpenMP thread stalls each region for a scheduler slice: measured
on this project's 2-core box at load ~4, `a * b + a` on 100k floats took 89 µs with 1 thread and
31 ms with 2, and a paper-preset record went from 0.16 to 1.9 CPU-seconds.

Workers use the spawn start method (no fork of a parent that may hold torch/OpenMP state or threads)
and ignore SIGINT: Ctrl-C is the parent's to handle, which stops handing out work, terminates the
workers and joins them, leaving no process behind. Workers hand records back as files in a private
temporary directory (see `render_record_to_file`), so a terminated worker never leaves half a
message in the executor's result pipe. At most `window` records are
submitted ahead of the one being consumed, so memory stays bounded however slow the consumer is.
"""

from __future__ import annotations

import multiprocessing
import os
import shutil
import signal
import tempfile
import threading
from collections import deque
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from typing import Iterable, Iterator

from core.errors import N3dmapError
from services.threads import usable_cpus


@dataclass(frozen=True, kw_only=True)
class RecordSpec:
    """Everything that determines one synthetic record (picklable, sent to workers)."""

    preset: str
    seed: int
    num_views: int | None = None
    num_frames: int | None = None
    moving_ego: bool = False
    sparse_depth: bool = False
    noise: float = 0.0
    world_overrides: tuple[tuple[str, object], ...] = ()  # (WorldConfig field, value) over the preset's world


def render_record(spec: RecordSpec) -> dict:
    """The record of `spec` (core.synthetic.generate_record on the CPU); same bytes in any process."""
    from core.presets import get_preset
    from core.synthetic import generate_record
    from core.synthetic.config import world_with

    preset = get_preset(spec.preset)
    world = world_with(preset, dict(spec.world_overrides))
    return generate_record(preset, seed=spec.seed, num_views=spec.num_views,
                           num_frames=spec.num_frames, moving_ego=spec.moving_ego,
                           sparse_depth=spec.sparse_depth, noise=spec.noise, world=world)


def render_record_to_file(spec: RecordSpec, path: str) -> str:
    """Worker side of the pool: render `spec`, write it to `path` as record npz bytes, return `path`.

    Why a file and not the return value: a record travels back through the executor's result pipe,
    and one at the paper preset is megabytes. Ctrl-C terminates the workers; one killed halfway
    through sending leaves a partial message that the executor's reader thread waits on forever, and
    shutdown(wait=True) joins that thread. The interrupted command hung once that way (SIGINT as the
    first record arrived; not reproduced on demand, so the cause is inferred). A path is a few bytes,
    written in one atomic pipe write."""
    from core.data.shards import encode_record

    tmp = f"{path}.tmp"
    with open(tmp, "wb") as f:
        f.write(encode_record(render_record(spec)))
    os.replace(tmp, path)
    return path


def _read_rendered(path: str, index: int) -> dict:
    """The record a worker wrote to `path` (validated, never unpickled); the file is removed."""
    from core.data.shards import decode_record

    try:
        with open(path, "rb") as f:
            data = f.read()
    finally:
        with suppress(OSError):
            os.remove(path)
    return decode_record(data, f"rendered record {index}")


# Below this many rendered pixels a job runs in-process: a worker's start-up (importing torch, ~2 CPU-s)
# would cost more than it saves. 20 M pixels ≈ 5 s of one core here (≈ 34 paper-preset records of
# 2×6 views at 128×384, ≈ 270 tiny ones).
POOL_MIN_PIXELS = 20_000_000


def default_jobs(*, records: int, pixels_per_record: int) -> int:
    """min(usable CPUs, 4, records) render processes (one torch thread each, so processes × threads never
    exceeds the CPUs), or 1 when the whole job is too small to repay
    the workers' start-up (POOL_MIN_PIXELS); more processes than cores only add memory and contention."""
    if records * pixels_per_record < POOL_MIN_PIXELS:
        return 1
    return max(1, min(usable_cpus(), 4, records))


def _init_worker() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    import torch

    torch.set_num_threads(1)


def _describe(index: int, spec: RecordSpec, e: BaseException) -> str:
    text = " ".join(str(e).split()) or type(e).__name__
    return f"record {index} (seed {spec.seed}): {type(e).__name__}: {text}"


@contextmanager
def _single_torch_thread() -> Iterator[None]:
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


@contextmanager
def _sigint_ignored_while_spawning() -> Iterator[None]:
    """Spawned children inherit an ignored SIGINT through exec, so a Ctrl-C during their start-up
    (before `_init_worker` runs) cannot print a KeyboardInterrupt traceback from a child."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def render_records(specs: Iterable[RecordSpec], *, jobs: int, window: int | None = None) -> Iterator[dict]:
    """Yield the record of each spec (`render_record(spec)`; from workers, its schema keys), in order.

    jobs: worker processes (1: render in this process, with one torch thread while doing so).
    window: records submitted ahead of the consumer (default 2·jobs; memory ≈ window records).
    A failure while rendering record i raises N3dmapError naming it (a record's own N3dmapError is
    re-raised as is); a worker that dies (killed, out of memory) raises N3dmapError too. Closing the
    generator early (an error downstream, Ctrl-C) cancels the queued records and terminates and joins
    the workers, so none outlives it.
    """
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    if jobs == 1:
        with _single_torch_thread():
            for i, spec in enumerate(specs):
                try:
                    record = render_record(spec)
                except N3dmapError:
                    raise
                except Exception as e:  # noqa: BLE001 - named per record, as in the pool path
                    raise N3dmapError(f"rendering failed: {_describe(i, spec, e)}") from e
                yield record
        return

    window = 2 * jobs if window is None else max(1, window)
    executor = ProcessPoolExecutor(max_workers=jobs, mp_context=multiprocessing.get_context("spawn"),
                                   initializer=_init_worker)
    pending: deque[tuple[int, RecordSpec, Future]] = deque()
    todo = iter(enumerate(specs))
    spool = tempfile.mkdtemp(prefix="n3dmap-render-")  # workers hand records over as files here

    def submit(i: int, spec: RecordSpec) -> Future:
        return executor.submit(render_record_to_file, spec, os.path.join(spool, f"{i:08d}.npz"))

    try:
        with _sigint_ignored_while_spawning():  # the first `jobs` submits start the workers
            for i, spec in todo:
                pending.append((i, spec, submit(i, spec)))
                if len(pending) >= window:
                    break
        while pending:
            i, spec, future = pending.popleft()
            try:
                record = _read_rendered(future.result(), i)
            except BrokenProcessPool:
                raise N3dmapError(f"a render worker process died while rendering record {i} "
                                  f"(seed {spec.seed}); killed, or out of memory? (try fewer --jobs)") from None
            except N3dmapError:
                raise
            except Exception as e:  # noqa: BLE001 - any failure in a worker becomes a one-line error
                raise N3dmapError(f"rendering failed in a worker: {_describe(i, spec, e)}") from None
            nxt = next(todo, None)
            if nxt is not None:
                pending.append((nxt[0], nxt[1], submit(*nxt)))
            yield record
    finally:
        for _, _, future in pending:
            future.cancel()
        if pending:  # stopped early (error downstream, Ctrl-C): records in flight are not wanted
            _stop_workers(executor)
        executor.shutdown(wait=True, cancel_futures=True)
        shutil.rmtree(spool, ignore_errors=True)


def _stop_workers(executor: ProcessPoolExecutor) -> None:
    """Terminate the workers now instead of waiting for their records in flight (seconds each at
    the paper preset with many views). Python 3.14 has `terminate_workers`; before it, the process
    handles are only reachable through the executor's `_processes`."""
    terminate = getattr(executor, "terminate_workers", None)
    if terminate is not None:
        terminate()
        return
    for process in list((getattr(executor, "_processes", None) or {}).values()):
        process.terminate()
