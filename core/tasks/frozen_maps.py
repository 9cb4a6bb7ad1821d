"""A bounded cache of what a frozen module computes per example, keyed by a digest of the example's inputs.

Why: a detector trained on frozen features (the paper's protocol, `DetectorTaskConfig.freeze_features`)
recomputes the same map of the same record and time step at every epoch — at 2 labelled records there are
4 distinct maps — and the mapper's forward was ~40 % of its step (small preset, one thread: 0.59 of 1.36 s).
Flow over frozen features (core.tasks.flow) recomputes the same pair of maps of a record at every epoch too.

Each example's outputs are computed alone (a batch of one), so their value does not depend on which examples
share its batch or on what the cache held before: a run resumed from a checkpoint, with an empty cache, gets
the same outputs bit for bit (while the cache is on; one that turned itself off computes whole batches, equal
up to float rounding). The cache empties itself when any of the frozen module's tensors changed
(weights loaded, a move to another device: each tensor's storage and version counter are part of the check)
or the autocast state did; it keeps the most recently used outputs within `max_bytes`.

A cache too small for the data it sees (the paper preset's 1024 records' maps against a budget that holds a
few dozen) would only cost: every example computed alone instead of in its batch, and hashed. So once it is
full (its first eviction, or an output too large to keep), it counts its next `PROBE_LOOKUPS` lookups; if
fewer than `MIN_HIT_RATE` of them hit, it empties itself and turns off (`enabled` False), and its owner then
computes the batch as it would without one. Counting from the first eviction, not from the start, keeps the
misses of filling it (which any cache has) out of the verdict.
"""

from __future__ import annotations

import hashlib
from collections import OrderedDict
from itertools import chain

import torch
from torch import nn


def _digest(tensors: list[torch.Tensor]) -> bytes:
    """A 128-bit digest of the tensors' dtypes, shapes and bytes."""
    h = hashlib.blake2b(digest_size=16)
    for t in tensors:
        t = t.detach().contiguous().cpu()
        h.update(f"{t.dtype}{tuple(t.shape)}".encode())
        if t.numel():
            h.update(t.reshape(-1).view(torch.uint8).numpy())  # the buffer itself, not a bytes copy
    return h.digest()


def _nbytes(tensors: tuple[torch.Tensor, ...]) -> int:
    return sum(t.numel() * t.element_size() for t in tensors)


PROBE_LOOKUPS = 256   # lookups, once the cache is full, whose hit rate is judged
MIN_HIT_RATE = 0.5    # below it the cache turns itself off


class FrozenMapCache:
    """`maps(mapper, rgb, depth, pix_T_cam, cam_T_ref)` -> the mapper's maps B×F×Z×Y×X under no_grad, each
    example's computed alone and kept for the next call with the same inputs; `outputs(module, compute,
    inputs)` the same for any computation of a frozen module. The caller keeps the module frozen and in eval
    mode (BatchNorm's running statistics: each example's output is then its own)."""

    def __init__(self, *, max_bytes: int) -> None:
        if max_bytes < 0:
            raise ValueError(f"FrozenMapCache: max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self._entries: OrderedDict[bytes, tuple[torch.Tensor, ...]] = OrderedDict()
        self._bytes = 0
        self._state: tuple | None = None
        self.hits = 0
        self.misses = 0
        self.enabled = True
        self._full = False            # an output was evicted or too large to keep: the probe counts from here
        self._probe = [0, 0]          # [hits, lookups] since the cache was full, until judged

    def __len__(self) -> int:
        return len(self._entries)

    def clear(self) -> None:
        self._entries.clear()
        self._bytes = 0

    def _check_state(self, module: nn.Module) -> None:
        """Empty the cache when the module's tensors or the autocast state differ from the last call's."""
        # Both devices' autocast: torch.is_autocast_enabled() without an argument reports CUDA's only, so maps
        # kept in fp32 were returned under CPU bf16 autocast (`train --precision bf16` on a CPU).
        state = (tuple((t.data_ptr(), t._version) for t in chain(module.parameters(), module.buffers())),
                 torch.is_autocast_enabled("cpu"), torch.is_autocast_enabled("cuda"),
                 torch.get_autocast_dtype("cpu"), torch.get_autocast_dtype("cuda"))
        if state != self._state:
            self.clear()
            self._state = state
            self._full, self._probe = False, [0, 0]   # a new module's outputs: the probe starts again

    def maps(self, mapper: nn.Module, rgb: torch.Tensor, depth: torch.Tensor, pix_T_cam: torch.Tensor,
             cam_T_ref: torch.Tensor) -> torch.Tensor:
        """rgb B×V×3×H×W, depth B×V×H×W, pix_T_cam B×…×4×4, cam_T_ref B×V×4×4 (the Mapper's inputs) -> B×F×Z×Y×X."""
        return self.outputs(mapper, lambda example: (mapper(*example),), [rgb, depth, pix_T_cam, cam_T_ref])[0]

    def outputs(self, module: nn.Module, compute, inputs: list[torch.Tensor]) -> tuple[torch.Tensor, ...]:
        """compute(example inputs, each 1×…) -> a tuple of 1×… tensors, for each example of the B×… `inputs`
        (from the cache when the same inputs came before and `module` has not changed) -> the tuple with each
        tensor B×… (the examples' outputs concatenated in order)."""
        if not self.enabled:
            raise RuntimeError("FrozenMapCache.outputs: the cache turned itself off (its hit rate was too low); "
                               "compute the batch directly")
        self._check_state(module)
        out = []
        with torch.no_grad():
            for b in range(inputs[0].shape[0]):
                example = [x[b:b + 1] for x in inputs]                  # each 1×…
                key = _digest(example)
                cached = self._entries.get(key)
                probing = self._full and self._probe[1] < PROBE_LOOKUPS
                if cached is not None:
                    self._entries.move_to_end(key)
                    self.hits += 1
                    self._probe[0] += probing
                else:
                    self.misses += 1
                    cached = tuple(compute(example))                    # each 1×…
                    self._keep(key, cached)
                self._probe[1] += probing
                out.append(cached)
        if self._probe[1] == PROBE_LOOKUPS:
            self._probe[1] += 1                                         # judged once
            if self._probe[0] < MIN_HIT_RATE * PROBE_LOOKUPS:
                self.enabled = False
                self.clear()
        return tuple(torch.cat(parts, dim=0) for parts in zip(*out))   # each B×…

    def _keep(self, key: bytes, value: tuple[torch.Tensor, ...]) -> None:
        size = _nbytes(value)
        if size > self.max_bytes:
            self._full = True
            return
        while self._bytes + size > self.max_bytes:
            self._full = True
            _, dropped = self._entries.popitem(last=False)
            self._bytes -= _nbytes(dropped)
        self._entries[key] = value
        self._bytes += size
