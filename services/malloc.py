"""glibc malloc settings of n3dmap's long-running processes, decided by measurement.

Two settings, each applied with `mallopt` (so they need no environment variable and no preloaded
allocator), each skipped where the environment already decides (glibc's own MALLOC_* variables) or where
the C library is not glibc:

1. `keep_heap()`: M_MMAP_MAX 0 and M_TRIM_THRESHOLD 1 GiB — every chunk comes from the heap and freed heap
   is kept for the next step. Why: glibc serves a chunk above its mmap threshold (at most 32 MiB) with a
   fresh mmap and unmaps it on free, so each training step's or stream frame's large tensors (the paper
   grid's 64 MiB feature maps, the small grid's 4 MiB ones) were faulted in page by page, every time.
   Measured (tests/benchmarks/bench_encoder.py, paper-grid encoder, 2 threads, one process per setting,
   alternating, nothing else running, load 1.3–1.6): forward 188–199 → 131–138 ms (0.85–0.89 → 1.22 × the
   same run's 2048² SGEMM rate), forward+backward fp32 0.67–0.68 → 0.44–0.45 s, bf16 0.43–0.45 → 0.29 s. The price: the process keeps its peak heap instead of
   returning it (RSS stays at the high-water mark), which is what a process that repeats the same step
   needs anyway. jemalloc and tcmalloc are not in the package index n3dmap installs from, and this gets
   the same effect (no page faults on reused memory) without a preload.
2. `limit_arenas(2)`: M_ARENA_MAX 2 — threads that allocate get their own arenas (up to 8 per core) and
   fragment them; the server's RSS crept up under load: +6–7 % in 1–3 min at 64 concurrent clients
   (tests/benchmarks/bench_soak.py, 2 CPUs), flat (+1 %) with 2 arenas at the same throughput. Must run
   before the process's threads first allocate (glibc fixes the limit when a thread first needs an arena).

`N3DMAP_MALLOC=default` turns both off (for comparisons, or an allocator preloaded by the user).
"""

from __future__ import annotations

import ctypes
import os
import sys

M_TRIM_THRESHOLD, M_MMAP_MAX, M_ARENA_MAX = -1, -4, -8  # glibc malloc.h parameter numbers
KEEP_HEAP_TRIM_BYTES = 1 << 30
ARENAS = 2


def _mallopt(*settings: tuple[int, int]) -> bool:
    if not sys.platform.startswith("linux") or os.environ.get("N3DMAP_MALLOC") == "default":
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        return all(bool(libc.mallopt(param, value)) for param, value in settings)
    except (OSError, AttributeError):  # not glibc (e.g. musl has no libc.so.6 / mallopt)
        return False


def keep_heap() -> bool:
    """Heap-only chunks, kept after free (see the module doc), unless MALLOC_MMAP_MAX_ or
    MALLOC_TRIM_THRESHOLD_ is set. True if applied."""
    if os.environ.get("MALLOC_MMAP_MAX_") or os.environ.get("MALLOC_TRIM_THRESHOLD_"):
        return False
    return _mallopt((M_MMAP_MAX, 0), (M_TRIM_THRESHOLD, KEEP_HEAP_TRIM_BYTES))


def limit_arenas(n: int = ARENAS) -> bool:
    """Cap glibc's malloc arenas at `n` (as MALLOC_ARENA_MAX=n would), unless MALLOC_ARENA_MAX is set.
    True if applied."""
    if os.environ.get("MALLOC_ARENA_MAX"):
        return False
    return _mallopt((M_ARENA_MAX, n))
