"""BenchConfig: everything `n3dmap bench paper` runs, as one typed, JSON-serialisable value.

`plan_for(preset, seeds=..., quick=...)` gives the default plan of a preset; the CLI's flags replace
single fields (`dataclasses.replace`). The plan fixes, for the whole benchmark:

- data: `train_episodes` records for training (moving ego on every second record) and
  `test_episodes` held-out records (generated from `data_seed + 1`, so no record is in both);
- seeds: one full set of trained models per seed (weights and data order; the data are shared);
- steps per stage: pretraining (contrastive and regression), detector, flow, egomotion;
- label budgets: numbers of labelled training records the detector gets (None = all of them);
- the detector variants: (pretraining arm, "frozen" | "finetuned") pairs; the random-init arm is
  trained end to end (frozen random features measure nothing the paper reports).

`quick=True` is the test profile: a handful of records and a few steps per stage, so the whole
pipeline runs in a couple of minutes on a 2-core CPU (numbers are then meaningless, only complete).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

from core.errors import N3dmapError

ARMS = ("random", "regression", "contrastive")          # pretraining arms, weakest first
PRETRAINED_ARMS = ("regression", "contrastive")          # arms that run a pretraining stage
MODES = ("frozen", "finetuned")
DEFAULT_VARIANTS: tuple[tuple[str, str], ...] = (
    ("random", "finetuned"),
    ("regression", "frozen"), ("regression", "finetuned"),
    ("contrastive", "frozen"), ("contrastive", "finetuned"),
)


class BenchConfigError(N3dmapError):
    """A benchmark option is out of range or inconsistent with the others."""


@dataclass(frozen=True)
class StageSteps:
    """Optimisation steps of each training stage."""

    pretrain: int
    detector: int
    flow: int
    egomotion: int

    def __post_init__(self) -> None:
        for name, value in asdict(self).items():
            if value < 1:
                raise BenchConfigError(f"steps of stage {name!r} must be >= 1, got {value}")


@dataclass(frozen=True)
class BenchConfig:
    """One `bench paper` run (see the module docstring)."""

    preset: str
    seeds: tuple[int, ...]
    train_episodes: int
    test_episodes: int
    label_budgets: tuple[int | None, ...]      # None: every training record is labelled
    steps: StageSteps
    detector_variants: tuple[tuple[str, str], ...] = DEFAULT_VARIANTS
    data_seed: int = 0
    batch_size: int | None = None              # records per step (None: the preset's default)
    workers: int = 0                           # 0: train in this process; N: Ray Train with N workers
    device: str = "auto"                       # auto | cpu | cuda
    retrieval_per_example: int = 10            # patch pairs per (record, target view): the paper's 10
    retrieval_cube: int = 3                    # side of the 3D feature cubes (2D patches: the eval kind's 5)
    moving_iou: float = 0.5                    # the paper's PR curves use 3D IoU 0.5
    flow2d_threshold_px: float = 1.0           # 2.5D baseline: pixels of 2D flow that count as motion
    flow2d_min_pixels: int = 20                # 2.5D baseline: smaller 2D clusters are dropped
    quick: bool = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "seeds", tuple(int(s) for s in self.seeds))
        object.__setattr__(self, "label_budgets", tuple(None if b is None else int(b) for b in self.label_budgets))
        object.__setattr__(self, "detector_variants", tuple((str(a), str(m)) for a, m in self.detector_variants))
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise BenchConfigError(f"seeds must be distinct and at least one, got {list(self.seeds)}")
        if self.train_episodes < 2 or self.test_episodes < 1:
            raise BenchConfigError(f"need >= 2 training and >= 1 test records, got {self.train_episodes} "
                                   f"and {self.test_episodes}")
        if not self.label_budgets:
            raise BenchConfigError("at least one label budget is needed")
        for b in self.label_budgets:
            if b is not None and not 1 <= b <= self.train_episodes:
                raise BenchConfigError(f"label budget {b} must lie in [1, {self.train_episodes}] "
                                       "(the training records)")
        for arm, mode in self.detector_variants:
            if arm not in ARMS or mode not in MODES:
                raise BenchConfigError(f"detector variant ({arm!r}, {mode!r}): arm must be one of {ARMS} "
                                       f"and mode one of {MODES}")
        if self.workers < 0:
            raise BenchConfigError(f"workers must be >= 0, got {self.workers}")
        if self.retrieval_per_example < 1 or self.retrieval_cube < 1 or self.retrieval_cube % 2 == 0:
            raise BenchConfigError("retrieval needs >= 1 pair per example and an odd cube size")

    @property
    def budgets_sorted(self) -> tuple[int | None, ...]:
        """Label budgets, smallest first, `None` (all) last."""
        return tuple(sorted(self.label_budgets, key=lambda b: self.train_episodes + 1 if b is None else b))

    def budget_records(self, budget: int | None) -> int:
        """How many records a budget labels."""
        return self.train_episodes if budget is None else budget

    def to_dict(self) -> dict:
        d = asdict(self)
        d["seeds"] = list(self.seeds)
        d["label_budgets"] = ["all" if b is None else b for b in self.label_budgets]
        d["detector_variants"] = [list(v) for v in self.detector_variants]
        return d


# Per preset: (train, test) episodes, label budgets, StageSteps — the full and the quick profile.
_PROFILES: dict[tuple[str, bool], dict] = {
    ("tiny", False): dict(train_episodes=12, test_episodes=8, label_budgets=(2, 6, None),
                          steps=StageSteps(pretrain=100, detector=40, flow=60, egomotion=60)),
    # small: sized so that 2 seeds finish in about 2 hours on a 2-core CPU (measured; README).
    ("small", False): dict(train_episodes=64, test_episodes=16, label_budgets=(2, 8, None),
                           steps=StageSteps(pretrain=300, detector=100, flow=100, egomotion=100)),
    ("paper", False): dict(train_episodes=1024, test_episodes=100, label_budgets=(8, 32, 128, 512, None),
                           steps=StageSteps(pretrain=50_000, detector=10_000, flow=10_000, egomotion=10_000)),
}
_QUICK = dict(train_episodes=4, test_episodes=2, label_budgets=(2, None),
              steps=StageSteps(pretrain=2, detector=2, flow=2, egomotion=2), retrieval_per_example=4,
              detector_variants=(("random", "finetuned"), ("regression", "frozen"), ("contrastive", "frozen"),
                                 ("contrastive", "finetuned")))


def plan_for(preset: str, *, seeds: tuple[int, ...] = (0,), quick: bool = False, **overrides) -> BenchConfig:
    """The default plan of `preset` (tiny, small, paper), with `overrides` replacing fields."""
    key = (preset, False)
    if key not in _PROFILES:
        raise BenchConfigError(f"unknown preset {preset!r}; choose one of {sorted(p for p, _ in _PROFILES)}")
    base = dict(_QUICK) if quick else dict(_PROFILES[key])
    base.update(overrides)
    return BenchConfig(preset=preset, seeds=tuple(seeds), quick=quick, **base)


def with_steps(config: BenchConfig, **steps) -> BenchConfig:
    """`config` with some stage steps replaced (pretrain=, detector=, flow=, egomotion=)."""
    return replace(config, steps=replace(config.steps, **steps))
