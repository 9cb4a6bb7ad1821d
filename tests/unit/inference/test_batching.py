"""The micro-batcher: batches by key, per-item results, bounded queue, deadlines, errors."""

import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor

import pytest

from services.inference.batching import BatchConfig, MicroBatcher
from services.inference.errors import NotReady, Overloaded, RequestTimeout


def _run(coro):
    return asyncio.run(coro)


def test_concurrent_requests_batch_by_key_and_get_their_own_results():
    calls = []

    def square_batch(key, items):
        calls.append((key, list(items)))
        time.sleep(0.02)  # the model is busy: later requests pile up into the next batch
        return [x * x for x in items]

    async def main():
        with ThreadPoolExecutor(1) as ex:
            b = MicroBatcher(square_batch, ex, config=BatchConfig(max_batch=4, max_wait_s=0.01, max_queue=100))
            b.start()
            keys = ["a" if i % 3 else "b" for i in range(20)]
            out = await asyncio.gather(*(b.submit(k, i, timeout_s=5) for i, k in enumerate(keys)))
            await b.stop()
            return keys, out

    keys, out = _run(main())
    assert [r for r, _ in out] == [i * i for i in range(20)]
    assert all(len(items) <= 4 for _, items in calls)
    assert sum(len(items) for _, items in calls) == 20
    for key, items in calls:  # every batch holds one key only
        assert all(keys[i] == key for i in items)
    assert max(s.batch_size for _, s in out) > 1


def test_full_queue_is_overloaded_not_unbounded():
    release = threading.Event()

    def blocked(key, items):
        release.wait(5)
        return items

    async def main():
        with ThreadPoolExecutor(1) as ex:
            b = MicroBatcher(blocked, ex, config=BatchConfig(max_batch=1, max_wait_s=0, max_queue=3))
            b.start()
            first = asyncio.ensure_future(b.submit("k", 0, timeout_s=5))
            await asyncio.sleep(0.05)  # item 0 is running now; the queue is empty
            queued = [asyncio.ensure_future(b.submit("k", i, timeout_s=5)) for i in (1, 2, 3)]
            await asyncio.sleep(0)
            with pytest.raises(Overloaded):
                await b.submit("k", 4, timeout_s=5)
            release.set()
            results = [r for r, _ in await asyncio.gather(first, *queued)]
            await b.stop()
            return results

    assert _run(main()) == [0, 1, 2, 3]


def test_deadline_and_model_errors_reach_the_caller():
    def slow_or_failing(key, items):
        if key == "fail":
            raise ValueError("model exploded")
        time.sleep(0.3)
        return items

    async def main():
        with ThreadPoolExecutor(1) as ex:
            b = MicroBatcher(slow_or_failing, ex, config=BatchConfig(max_batch=2, max_wait_s=0, max_queue=8))
            with pytest.raises(NotReady):
                await b.submit("k", 1, timeout_s=1)
            b.start()
            with pytest.raises(RequestTimeout):
                await b.submit("slow", 1, timeout_s=0.05)
            with pytest.raises(ValueError, match="exploded"):
                await b.submit("fail", 1, timeout_s=2)
            assert (await b.submit("ok", 7, timeout_s=2))[0] == 7  # still serving afterwards
            assert await b.drain(1.0)
            with pytest.raises(NotReady):
                await b.submit("k", 1, timeout_s=1)
            await b.stop()

    _run(main())


def test_a_cancelled_request_leaves_the_queue_and_is_never_run():
    release, ran = threading.Event(), []

    def blocked(key, items):
        ran.extend(items)
        release.wait(5)
        return items

    async def main():
        with ThreadPoolExecutor(1) as ex:
            b = MicroBatcher(blocked, ex, config=BatchConfig(max_batch=1, max_wait_s=0, max_queue=2))
            b.start()
            first = asyncio.ensure_future(b.submit("k", 0, timeout_s=5))
            await asyncio.sleep(0.05)                 # item 0 runs; the model is busy
            gone = asyncio.ensure_future(b.submit("k", 1, timeout_s=5))
            await asyncio.sleep(0.01)
            assert b.queued == 1
            gone.cancel()                             # the caller went away (a gRPC cancel, a passed deadline)
            with pytest.raises(asyncio.CancelledError):
                await gone
            assert b.queued == 0                      # its queue slot is free again
            with pytest.raises(RequestTimeout, match="within 0 s"):
                await b.submit("k", 2, timeout_s=0)   # a deadline already passed: refused at once, not granted more
            last = asyncio.ensure_future(b.submit("k", 3, timeout_s=5))
            release.set()
            out = [r for r, _ in await asyncio.gather(first, last)]
            await b.stop()
            return out

    assert _run(main()) == [0, 3]
    assert ran == [0, 3]                              # neither the cancelled nor the expired request ran


def test_one_bad_request_in_a_batch_fails_alone():
    calls = []

    def picky(key, items):
        calls.append(list(items))
        if any(x < 0 for x in items):
            raise ValueError(f"negative input among {items}")
        time.sleep(0.02)
        return [x * 10 for x in items]

    observed = []

    async def main():
        with ThreadPoolExecutor(1) as ex:
            b = MicroBatcher(picky, ex, config=BatchConfig(max_batch=4, max_wait_s=0.05, max_queue=8),
                             observe=lambda key, size, waits, model_s: observed.append((size, len(waits), model_s)))
            b.start()
            out = await asyncio.gather(*(b.submit("k", x, timeout_s=5) for x in (1, -2, 3)), return_exceptions=True)
            await b.stop()
            return out

    out = _run(main())
    assert [o[0] for o in (out[0], out[2])] == [10, 30] and isinstance(out[1], ValueError)
    assert calls[0] == [1, -2, 3] and sorted(map(tuple, calls[1:])) == [(-2,), (1,), (3,)]
    # each model call observed as what it was: the failed batch of 3 (with the 3 queue waits), then 3 batches of 1
    assert [(size, waits) for size, waits, _ in observed] == [(3, 3), (1, 0), (1, 0), (1, 0)]
    # a rerun request's stats are its own call's: a batch of one, that call's model time (picky sleeps 20 ms)
    for result, stats in (out[0], out[2]):
        assert stats.batch_size == 1 and 0.015 < stats.model_s < 5
