"""Small matplotlib figures shared by the evaluation reports (Agg, no display)."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure


def histograms(series: dict[str, np.ndarray], *, xlabel: str, title: str, bins: int = 30) -> Figure:
    """Overlaid histograms of one error per method (name -> values)."""
    fig = Figure(figsize=(5, 3.2))
    ax = fig.subplots()
    finite = [v[np.isfinite(v)] for v in series.values() if len(v)]
    hi = max((float(v.max()) for v in finite if len(v)), default=1.0) or 1.0
    edges = np.linspace(0.0, hi, bins + 1)
    for name, values in series.items():
        ax.hist(values, bins=edges, alpha=0.5, label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("pairs")
    ax.set_title(title)
    ax.legend()
    return fig


def image_grid(images: list[tuple[str, np.ndarray]], *, cmap: str = "viridis", suptitle: str = "",
               vmin=None, vmax=None) -> Figure:
    """Side-by-side 2D maps (title, H×W array) with colour bars; NaN shows as blank."""
    fig = Figure(figsize=(3.6 * len(images), 3.4))
    axes = np.atleast_1d(fig.subplots(1, len(images)))
    for ax, (title, img) in zip(axes, images):
        im = ax.imshow(img, cmap=cmap, origin="lower", vmin=vmin, vmax=vmax)
        ax.set_title(title)
        ax.set_xlabel("x (voxels)")
        ax.set_ylabel("z (voxels)")
        fig.colorbar(im, ax=ax, shrink=0.8)
    if suptitle:
        fig.suptitle(suptitle)
    return fig
