"""Presets: typed configs composed in Python (no global hyperparameter module).

`tiny` is for tests, `small` for CPU training, `paper` reproduces the paper's appendix
(128×32×128 voxels over 32×8×32 m, 128×384 images, batch 4) on a GPU.

The map grid is centred on the ego in `ref` (X right, Y down, Z forward). The ground plane lies at
ref y = +`ground_y` (below the ref origin, since Y points down), so the grid's Y range covers
some ground and what stands on it.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace

from core.errors import ConfigError
from core.geometry.grid import GridConfig


@dataclass(frozen=True)
class CameraConfig:
    """Pinhole cameras of the rig: image size and horizontal field of view."""

    H: int
    W: int
    hfov_deg: float = 90.0


@dataclass(frozen=True)
class TrainDefaults:
    """Default optimisation settings of a preset (CLI flags override them)."""

    batch_size: int = 2
    lr: float = 1e-3
    flow_lr: float = 1e-4
    steps: int = 200
    checkpoint_every: int = 50
    contrastive_samples: int = 960


@dataclass(frozen=True)
class Preset:
    """Everything a preset fixes: grid, cameras, data generation defaults, model widths, training."""

    name: str
    grid: GridConfig
    camera: CameraConfig
    num_views: int
    num_frames: int
    ground_y: float = 2.0
    feature_dim: int = 32          # F: channels of the 3D feature map
    embed_dim: int = 32            # E: channels of the 2D embeddings
    encoder_width: int = 64        # channels of the first 3D encoder stage (paper: 64)
    encoder_full_res: int = 0      # channels of the encoder's full-resolution branch (0: the paper's layers)
    depth_planes: int = 64         # log-spaced planes of the 3D->2D projection (max-pooled ×8)
    depth_min: float = 1.0         # nearest projection plane, metres
    depth_max: float = 40.0        # farthest projection plane, metres
    train: TrainDefaults = field(default_factory=TrainDefaults)

    def with_overrides(self, **kwargs) -> "Preset":
        return replace(self, **kwargs)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["grid"] = self.grid.to_dict()
        return d

    @staticmethod
    def from_dict(d: dict) -> "Preset":
        return Preset(
            name=d["name"], grid=GridConfig.from_dict(d["grid"]), camera=CameraConfig(**d["camera"]),
            num_views=d["num_views"], num_frames=d["num_frames"], ground_y=d["ground_y"],
            feature_dim=d["feature_dim"], embed_dim=d["embed_dim"], encoder_width=d["encoder_width"],
            encoder_full_res=d.get("encoder_full_res", 0),  # absent in bundles made before the branch existed
            depth_planes=d["depth_planes"], depth_min=d["depth_min"], depth_max=d["depth_max"],
            train=TrainDefaults(**d["train"]),
        )


def _grid(Z: int, Y: int, X: int) -> GridConfig:
    # 32 m (x) × 8 m (y) × 32 m (z) around the ego; y from -4 (above) to +4 (below, ground at +2).
    return GridConfig(xmin=-16.0, xmax=16.0, ymin=-4.0, ymax=4.0, zmin=-16.0, zmax=16.0, Z=Z, Y=Y, X=X)


TINY = Preset(
    name="tiny", grid=_grid(32, 8, 32), camera=CameraConfig(H=64, W=192, hfov_deg=90.0),
    num_views=3, num_frames=2, feature_dim=8, embed_dim=8, encoder_width=8, depth_planes=32,
    train=TrainDefaults(batch_size=2, steps=20, checkpoint_every=10, contrastive_samples=128),
)

SMALL = Preset(
    name="small", grid=_grid(64, 16, 64), camera=CameraConfig(H=64, W=192, hfov_deg=90.0),
    num_views=4, num_frames=2, feature_dim=16, embed_dim=16, encoder_width=16, depth_planes=64,
    train=TrainDefaults(batch_size=2, steps=500, checkpoint_every=100, contrastive_samples=480),
)

PAPER = Preset(
    name="paper", grid=_grid(128, 32, 128), camera=CameraConfig(H=128, W=384, hfov_deg=90.0),
    num_views=6, num_frames=2, feature_dim=32, embed_dim=32, encoder_width=64, depth_planes=128,
    train=TrainDefaults(batch_size=4, steps=200_000, checkpoint_every=1000, contrastive_samples=960),
)

PRESETS: dict[str, Preset] = {p.name: p for p in (TINY, SMALL, PAPER)}


def get_preset(name: str) -> Preset:
    """Look up a preset by name; a clear error lists the known ones."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ConfigError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}") from None
