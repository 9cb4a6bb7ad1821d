"""Seeds a training run derives from its own seed, so that what it draws depends on where it is, not on
how it got there.

Why: the loop seeds torch once at the start of every `train_loop` call (identical initial weights on
every rank), and a resumed run is a new call. The tasks draw their time steps, views, contrastive
negatives, synthetic motions and pose perturbations from torch's global generator, so without a seed
per step every resume replayed the first call's draws — and the benchmark's held-out stopping rule
trains in chunks of 100–200 steps, each a resume: a 2000-step flow stage saw the same 100 synthetic
motions twenty times. Seeding each step from (run seed, rank, step) gives step s the same draws whether
the run was cut before it or not, and every rank its own draws. (Which records form step s's batch still
depends on the cuts: a resumed run starts an epoch index of its own, loop.py.)

`np.random.SeedSequence` mixes the parts (no collisions such as seed·1000 + epoch·10 + rank had once
the epoch index became a step count in the hundreds).
"""

from __future__ import annotations

import numpy as np


def _mix(*parts: int) -> int:
    """A 63-bit seed from non-negative ints, well mixed (distinct tuples give unrelated seeds)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1, dtype=np.uint64)[0] >> 1)


def step_seed(seed: int, rank: int, step: int) -> int:
    """The seed of torch's generators before optimizer step `step` + 1 of rank `rank` of run `seed`."""
    return _mix(seed, rank, step)


def shuffle_seed(seed: int, epoch: int, rank: int) -> int:
    """The seed of one rank's local shuffle of one epoch (Ray Data's `local_shuffle_seed`, a 32-bit int)."""
    return _mix(seed, epoch, rank) & 0x7FFFFFFF
