"""3D connected components of a boolean volume laid out Z×Y×X (docs/conventions.md#tensor-layouts)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from core.errors import ShapeError


def to_numpy(volume) -> np.ndarray:
    """numpy view of a numpy array or a (CPU or GPU) torch tensor."""
    if hasattr(volume, "detach"):
        return volume.detach().cpu().numpy()
    return np.asarray(volume)


def connected_components(mask, *, connectivity: int = 26) -> tuple[np.ndarray, int]:
    """Label the connected True regions of `mask`.

    mask: Z×Y×X bool (numpy or torch). connectivity: 6 (faces), 18 (faces + edges) or 26 (all
    neighbours). Returns (labels Z×Y×X int32 with 0 = background and 1..count the components, count).
    """
    m = to_numpy(mask).astype(bool)
    if m.ndim != 3:
        raise ShapeError(f"mask: expected Z×Y×X, got {'×'.join(map(str, m.shape))}")
    rank = {6: 1, 18: 2, 26: 3}.get(connectivity)
    if rank is None:
        raise ValueError(f"connectivity must be 6, 18 or 26, got {connectivity}")
    labels, count = ndimage.label(m, structure=ndimage.generate_binary_structure(3, rank))
    return labels.astype(np.int32), int(count)


def component_indices(labels: np.ndarray, count: int) -> list[np.ndarray]:
    """Voxel indices of each component 1..count: a list of N_k×3 int arrays in (z, y, x) order."""
    flat = labels.reshape(-1)
    order = np.argsort(flat, kind="stable")
    bounds = np.searchsorted(flat[order], np.arange(1, count + 2))
    zyx = np.stack(np.unravel_index(order, labels.shape), axis=-1)  # (Z·Y·X)×3, sorted by label
    return [zyx[bounds[k]:bounds[k + 1]] for k in range(count)]
