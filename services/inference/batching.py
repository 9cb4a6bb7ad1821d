"""Micro-batching of concurrent requests over one model executor, with a bounded queue.

Requests carry a batch key (route + input shapes + options); requests with equal keys can run as one
model call. One worker task takes the oldest waiting request, waits at most `max_wait_s` (from that
request's arrival) for up to `max_batch` requests with its key, and runs them in the executor. While
the model runs, new requests queue up, so batches grow with load without adding latency when idle.

Overload is explicit: past `max_queue` waiting requests `submit` raises Overloaded at once.
A request whose deadline passes raises RequestTimeout; if it had not started it is dropped from
the queue, if it had, its result is discarded.
"""

from __future__ import annotations

import asyncio
import time
from collections import deque
from concurrent.futures import Executor
from dataclasses import dataclass, field
from typing import Any, Callable, Hashable

from services.inference.errors import NotReady, Overloaded, RequestTimeout


@dataclass(frozen=True)
class BatchConfig:
    max_batch: int = 8
    max_wait_s: float = 0.005
    max_queue: int = 64

    def __post_init__(self) -> None:
        if self.max_batch < 1 or self.max_queue < 1 or self.max_wait_s < 0:
            raise ValueError(f"bad batching config {self}")


@dataclass
class BatchStats:
    """What one request saw: seconds queued, seconds in the model call, requests in its batch."""

    queue_s: float
    model_s: float
    batch_size: int


@dataclass
class _Pending:
    key: Hashable
    item: Any
    arrived: float
    future: asyncio.Future = field(repr=False)


# run_batch(key, items) -> one result per item, in order. Runs in the executor thread.
RunBatch = Callable[[Hashable, list], list]
# observe(key, batch_size, queue_waits_s, model_s): a hook for metrics.
Observe = Callable[[Hashable, int, list[float], float], None]


class MicroBatcher:
    def __init__(self, run_batch: RunBatch, executor: Executor, *, config: BatchConfig,
                 observe: Observe | None = None):
        self._run_batch = run_batch
        self._executor = executor
        self._config = config
        self._observe = observe
        self._queue: deque[_Pending] = deque()
        self._wakeup: asyncio.Event | None = None
        self._worker: asyncio.Task | None = None
        self._closing = False
        self._running = 0  # requests inside a model call now

    @property
    def queued(self) -> int:
        return len(self._queue)

    @property
    def in_flight(self) -> int:
        return len(self._queue) + self._running

    def start(self) -> None:
        self._wakeup = asyncio.Event()
        self._worker = asyncio.get_running_loop().create_task(self._work(), name="micro-batcher")

    async def submit(self, key: Hashable, item: Any, *, timeout_s: float | None) -> tuple[Any, BatchStats]:
        """Queue one request; wait for (its result, its BatchStats)."""
        if self._closing or self._worker is None:
            raise NotReady("the runtime is not accepting requests (starting or shutting down)")
        if len(self._queue) >= self._config.max_queue:
            raise Overloaded(f"request queue is full ({self._config.max_queue} waiting); retry later")
        pending = _Pending(key=key, item=item, arrived=time.perf_counter(),
                           future=asyncio.get_running_loop().create_future())
        self._queue.append(pending)
        self._wakeup.set()
        try:
            return await asyncio.wait_for(asyncio.shield(pending.future), timeout_s)
        except (asyncio.TimeoutError, asyncio.CancelledError) as e:
            # Timed out, or the caller's task was cancelled (a gRPC client cancelled or its deadline passed; an HTTP
            # client that disconnects does not cancel its request under uvicorn, so it still runs): a request
            # still queued leaves the queue, so that no model time and no queue slot goes to an answer no one
            # will read; one already in a model call finishes unread.
            if pending in self._queue:
                self._queue.remove(pending)
            pending.future.cancel()
            if isinstance(e, asyncio.CancelledError):
                raise
            raise RequestTimeout(f"request did not finish within {timeout_s:g} s") from None

    async def drain(self, timeout_s: float) -> bool:
        """Stop accepting, let queued and running requests finish; True if all did in time."""
        self._closing = True
        deadline = time.perf_counter() + timeout_s
        while self.in_flight and time.perf_counter() < deadline:
            await asyncio.sleep(0.01)
        return self.in_flight == 0

    async def stop(self) -> None:
        self._closing = True
        if self._worker is not None:
            self._worker.cancel()
            try:
                await self._worker
            except asyncio.CancelledError:
                pass
        for p in self._queue:
            if not p.future.done():
                p.future.set_exception(NotReady("the runtime shut down"))
        self._queue.clear()

    async def _work(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            while not self._queue:
                self._wakeup.clear()
                await self._wakeup.wait()
            head = self._queue[0]
            # Wait for company: until the batch is full or the head has waited max_wait_s.
            while (self._count(head.key) < self._config.max_batch
                   and time.perf_counter() - head.arrived < self._config.max_wait_s):
                self._wakeup.clear()
                remaining = self._config.max_wait_s - (time.perf_counter() - head.arrived)
                try:
                    await asyncio.wait_for(self._wakeup.wait(), max(remaining, 0.0))
                except asyncio.TimeoutError:
                    break
                if not self._queue or self._queue[0] is not head:
                    break  # head timed out meanwhile
            batch = self._take(self._queue[0].key) if self._queue else []
            if not batch:
                continue
            waits = [time.perf_counter() - p.arrived for p in batch]
            self._running = len(batch)
            try:
                outcomes = await self._run(loop, batch, waits)
            finally:
                self._running = 0
            for p, (result, error, stats) in zip(batch, outcomes):
                if p.future.done():
                    continue
                if error is not None:
                    p.future.set_exception(error)
                else:
                    p.future.set_result((result, stats))

    async def _run(self, loop, batch: list[_Pending], waits: list[float]
                   ) -> list[tuple[Any, BaseException | None, BatchStats | None]]:
        """(result, error, stats) per request of `batch`. A failed batch of several is run again one request at a
        time: an error one request's content causes (a degenerate scene, a shape the model refuses) must reach that
        request alone — delivered to the whole batch, it answered 4xx to callers whose input was valid. Each model
        call is observed as what it was (the failed batch, then each rerun as a batch of one; each request's queue wait
        once), and a rerun request's stats are its own call's."""
        try:
            results, model_s = await self._timed_call(loop, batch, waits)
            return [(r, None, BatchStats(queue_s=w, model_s=model_s, batch_size=len(batch)))
                    for r, w in zip(results, waits)]
        except Exception as e:
            if len(batch) == 1:
                return [(None, e, None)]
        outcomes = []
        for p, w in zip(batch, waits):
            if p.future.done():   # its caller timed out or went away meanwhile: no model time for it
                outcomes.append((None, None, None))
                continue
            try:
                (result,), model_s = await self._timed_call(loop, [p], [])   # its queue wait is observed once
                outcomes.append((result, None, BatchStats(queue_s=w, model_s=model_s, batch_size=1)))
            except Exception as e:
                outcomes.append((None, e, None))
        return outcomes

    async def _timed_call(self, loop, batch: list[_Pending], waits: list[float]) -> tuple[list, float]:
        """(results, model seconds) of one model call, observed whether it succeeds or fails (with `waits`, the queue
        waits that call observes)."""
        started = time.perf_counter()
        try:
            results = await self._call(loop, batch)
        finally:
            model_s = time.perf_counter() - started
            if self._observe is not None:
                self._observe(batch[0].key, len(batch), waits, model_s)
        return results, model_s

    async def _call(self, loop, batch: list[_Pending]) -> list:
        results = await loop.run_in_executor(self._executor, self._run_batch, batch[0].key, [p.item for p in batch])
        if len(results) != len(batch):
            raise RuntimeError(f"batch of {len(batch)} gave {len(results)} results")
        return results

    def _count(self, key: Hashable) -> int:
        return sum(1 for p in self._queue if p.key == key)

    def _take(self, key: Hashable) -> list[_Pending]:
        batch, rest = [], deque()
        for p in self._queue:
            if p.key == key and len(batch) < self._config.max_batch and not p.future.done():
                batch.append(p)
            elif not p.future.done():
                rest.append(p)
        self._queue = rest
        return batch
