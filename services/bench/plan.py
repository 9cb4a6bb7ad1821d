"""BenchConfig: everything `n3dmap bench paper` runs, as one typed, JSON-serialisable value.

`plan_for(preset, seeds=..., quick=...)` gives the default plan of a preset; the CLI's flags replace
single fields (`dataclasses.replace`). The plan fixes, for the whole benchmark:

- data: `train_episodes` records for training (moving ego on every second record),
  `test_episodes` test records (generated from `data_seed + 1`) and `val_episodes` validation records
  for the stopping rules (from `data_seed + 2`), so no record is in two of them;
- seeds: one full set of trained models per seed (weights and data order; the data are shared);
- a stopping rule per stage (services.bench.stopping): the two pretrainings (contrastive and regression)
  train one fixed number of steps, the same for both (`_pretraining`: the claims compare the objectives,
  not how long each ran); the occupancy module, flow and egomotion train until their loss on
  `val_episodes` held-out records stops improving (bounded); the detector trains a fixed number of epochs
  over its labelled records (bounded);
- label budgets: numbers of labelled training records the detector gets (None = all of them);
- label draws: at the smallest budget below all (the few-label claims read it) the detector is trained
  `label_draws` times, draw d on records [d·N, (d+1)·N) of the training set (disjoint; an even N keeps
  static- and moving-camera records alike), and its rows are the mean over the draws: one draw of 2
  records is a coin flip for a 0.02 margin (measured above `_PROFILES`); larger budgets use the first N;
- the detector variants: (pretraining arm, "frozen" | "finetuned") pairs; the random-init arm is
  trained end to end (frozen random features measure nothing the paper reports);
- `task_options`: extra task options per kind of stage (TASK_OPTION_KINDS), on top of the tasks'
  defaults, for running the benchmark with a recipe other than the defaults (e.g. pretraining's matching
  term and a wider flow window): "mapper" goes to every stage that builds a mapper (pretraining, occupancy,
  detector, flow; e.g. `encoder_full_res`, which they must all agree on), the others to their stages. The options that
  define the benchmark's arms (PROTOCOL_OPTIONS) cannot be set this way. Every arm gets the same options,
  with one exception: "pretrain_contrastive" gives the contrastive pretraining options of its objective's own
  construction that view regression has no counterpart of (CONTRASTIVE_ONLY_OPTIONS, e.g. `shift_positives`,
  where its positives come from), on top of "pretrain"; nothing else can be given to one arm;
- `world`: fields of the synthetic world (core.synthetic.config.WorldConfig) changed from the preset's for
  all three datasets, e.g. camera photometrics `{"exposure_std": 0.3, "pixel_noise_std": 0.03}` (default
  none: the preset's world, and a plan without the field reads as before).

`quick=True` is the test profile: a handful of records and 2 fixed steps per stage, so the whole
pipeline runs in well under a minute on a 2-core CPU (numbers are then meaningless, only complete, and
the report gives no verdicts).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace

from core.errors import N3dmapError
from services.bench.stopping import StageRule

ARMS = ("random", "regression", "contrastive")          # pretraining arms, weakest first
PRETRAINED_ARMS = ("regression", "contrastive")          # arms that run a pretraining stage
# Occupancy rows: the module trained by the paper's protocol at the balanced threshold chosen on the validation
# records (the row the claim reads), the same module at 0.5, then each pretraining's head at 0.5.
OCCUPANCY_MODULE = "contrastive, occupancy module, balanced threshold"
OCCUPANCY_MODULE_AT_HALF = "contrastive, occupancy module, threshold 0.5"
OCCUPANCY_ROWS = (OCCUPANCY_MODULE, OCCUPANCY_MODULE_AT_HALF, *(f"{arm}, pretraining head" for arm in PRETRAINED_ARMS))
MODES = ("frozen", "finetuned")
DEFAULT_VARIANTS: tuple[tuple[str, str], ...] = (
    ("random", "finetuned"),
    ("regression", "frozen"), ("regression", "finetuned"),
    ("contrastive", "frozen"), ("contrastive", "finetuned"),
)
# The rows the detection claims read (services.bench.claims.CLAIM_DETECTOR_MODES: the paper's protocol, pretrained
# arms on frozen features and random init end to end). The small plan runs only these: the pretrained arms'
# fine-tuned detectors are read by no claim and cost each seed ~8 h on the 2-core CPU (12 detectors of 800-1280
# steps at ~2.5-3 s per step, three seeds time-sliced; session 24); `bench paper --detector-variants` adds them.
JUDGED_VARIANTS: tuple[tuple[str, str], ...] = (
    ("random", "finetuned"), ("regression", "frozen"), ("contrastive", "frozen"),
)


# Kinds of stage `BenchConfig.task_options` may give options to ("mapper": every stage that builds one;
# "pretrain_contrastive": the contrastive arm's pretraining only, CONTRASTIVE_ONLY_OPTIONS only).
TASK_OPTION_KINDS = ("mapper", "pretrain", "pretrain_contrastive", "occupancy", "detector", "flow_features",
                     "flow_volume")
# Options the benchmark sets itself to define its arms and protocol.
PROTOCOL_OPTIONS = ("objective", "inputs", "labels", "freeze_features")
# Pretraining options only the contrastive objective has (PretrainConfig refuses them for regression): how its
# negatives and positives are drawn. "mapper" and "pretrain" options go to every arm, so there they are refused
# (rather than fail at the regression arm's stage); "pretrain_contrastive" takes these and only these, so that
# the arms differ in their objective alone.
CONTRASTIVE_ONLY_OPTIONS = ("coeff_local_negatives", "local_negative_radius", "shift_positives")


class BenchConfigError(N3dmapError):
    """A benchmark option is out of range or inconsistent with the others."""


@dataclass(frozen=True)
class StageRules:
    """How long each training stage trains (services.bench.stopping.StageRule)."""

    pretrain: StageRule
    detector: StageRule
    flow: StageRule
    egomotion: StageRule
    occupancy: StageRule

    def __post_init__(self) -> None:
        for name, rule in vars(self).items():
            if not isinstance(rule, StageRule):
                raise BenchConfigError(f"stage {name!r} needs a StageRule, got {rule!r}")

    def to_dict(self) -> dict:
        return {name: rule.to_dict() for name, rule in vars(self).items()}

    @staticmethod
    def from_dict(d: dict) -> "StageRules":
        missing = sorted(set(STAGE_NAMES) - set(d))
        if missing:
            raise BenchConfigError(f"the plan's rules lack {missing} (a plan of an older n3dmap); use a new --out")
        return StageRules(**{name: StageRule(**d[name]) for name in STAGE_NAMES})


# Training stages that have a stopping rule (StageRules' fields; the CLI's --<name>-steps).
STAGE_NAMES = tuple(f.name for f in fields(StageRules))


@dataclass(frozen=True)
class BenchConfig:
    """One `bench paper` run (see the module docstring)."""

    preset: str
    seeds: tuple[int, ...]
    train_episodes: int
    test_episodes: int
    label_budgets: tuple[int | None, ...]      # None: every training record is labelled
    rules: StageRules
    label_draws: int = 1                       # disjoint label sets at the smallest budget (rows: their mean)
    val_episodes: int = 8                      # held-out records of the plateau rules (never the test set)
    detector_variants: tuple[tuple[str, str], ...] = DEFAULT_VARIANTS
    data_seed: int = 0
    batch_size: int | None = None              # records per step (None: the preset's default)
    workers: int = 0                           # 0: train in this process; N: Ray Train with N workers
    device: str = "auto"                       # auto | cpu | cuda
    precision: str = "fp32"                    # every training stage's --precision (fp32 | bf16)
    retrieval_per_example: int = 10            # patch pairs per (record, target view): the paper's 10
    retrieval_cube: int = 3                    # side of the 3D feature cubes (2D patches: the eval kind's 5)
    moving_iou: float = 0.5                    # the paper's PR curves use 3D IoU 0.5
    flow2d_threshold_px: float = 1.0           # 2.5D baseline: pixels of 2D flow that count as motion
    flow2d_min_pixels: int = 20                # 2.5D baseline: smaller 2D clusters are dropped
    quick: bool = False
    task_options: dict = field(default_factory=dict)  # {kind in TASK_OPTION_KINDS: {option: value}}
    world: dict = field(default_factory=dict)  # {WorldConfig field: value} over the preset's synthetic world

    def __post_init__(self) -> None:
        object.__setattr__(self, "seeds", tuple(int(s) for s in self.seeds))
        object.__setattr__(self, "label_budgets", tuple(None if b is None else int(b) for b in self.label_budgets))
        object.__setattr__(self, "detector_variants", tuple((str(a), str(m)) for a, m in self.detector_variants))
        if not self.seeds or len(set(self.seeds)) != len(self.seeds):
            raise BenchConfigError(f"seeds must be distinct and at least one, got {list(self.seeds)}")
        if self.train_episodes < 2 or self.test_episodes < 1 or self.val_episodes < 2:
            raise BenchConfigError(f"need >= 2 training, >= 2 validation and >= 1 test records, got "
                                   f"{self.train_episodes}, {self.val_episodes} and {self.test_episodes}")
        if not self.label_budgets:
            raise BenchConfigError("at least one label budget is needed")
        for b in self.label_budgets:
            if b is not None and not 1 <= b <= self.train_episodes:
                raise BenchConfigError(f"label budget {b} must lie in [1, {self.train_episodes}] "
                                       "(the training records)")
        if self.label_draws < 1:
            raise BenchConfigError(f"label_draws must be >= 1, got {self.label_draws}")
        few = self.budgets_sorted[0]
        if few is not None and self.label_draws * few > self.train_episodes:
            raise BenchConfigError(f"label_draws {self.label_draws} at the smallest label budget {few} needs "
                                   f"{self.label_draws} disjoint sets of that many records, more than the "
                                   f"{self.train_episodes} training records")
        if not self.detector_variants or len(set(self.detector_variants)) != len(self.detector_variants):
            raise BenchConfigError(f"detector variants must be distinct and at least one, got "
                                   f"{['/'.join(v) for v in self.detector_variants]}")
        for arm, mode in self.detector_variants:
            if arm not in ARMS or mode not in MODES:
                raise BenchConfigError(f"detector variant ({arm!r}, {mode!r}): arm must be one of {ARMS} "
                                       f"and mode one of {MODES}")
        if self.workers < 0:
            raise BenchConfigError(f"workers must be >= 0, got {self.workers}")
        if self.workers > self.budget_records(few):
            # refused here, not at the first detector stage hours into the run
            raise BenchConfigError(f"workers {self.workers}: the smallest label budget labels "
                                   f"{self.budget_records(few)} record(s) and every Ray worker needs at least one; "
                                   "use at most that many workers or a larger smallest budget")
        if self.precision not in ("fp32", "bf16"):
            raise BenchConfigError(f"precision must be fp32 or bf16, got {self.precision!r}")
        if self.retrieval_per_example < 1 or self.retrieval_cube < 1 or self.retrieval_cube % 2 == 0:
            raise BenchConfigError("retrieval needs >= 1 pair per example and an odd cube size")
        from core.eval.protocols.moving import IOUS as MOVING_IOUS
        if self.moving_iou not in MOVING_IOUS:   # the protocol scores AP at these only: another gave no AP at all
            raise BenchConfigError(f"moving_iou must be one of {MOVING_IOUS} (the IoUs the moving-object protocol "
                                   f"scores), got {self.moving_iou!r}")
        if not isinstance(self.task_options, dict):
            raise BenchConfigError(f"task_options must map a stage kind to options, got {self.task_options!r}")
        for kind, options in self.task_options.items():
            if kind not in TASK_OPTION_KINDS:
                raise BenchConfigError(f"task_options: unknown stage kind {kind!r}; choose from {TASK_OPTION_KINDS}")
            if not isinstance(options, dict):
                raise BenchConfigError(f"task_options[{kind!r}] must be an object of task options, got {options!r}")
            fixed = sorted(set(options) & set(PROTOCOL_OPTIONS))
            if fixed:
                raise BenchConfigError(f"task_options[{kind!r}] sets {fixed}: the benchmark sets those itself "
                                       "(they define its arms)")
            one_arm = sorted(k for k in CONTRASTIVE_ONLY_OPTIONS if options.get(k))
            if one_arm and kind in ("mapper", "pretrain"):
                raise BenchConfigError(f"task_options[{kind!r}] sets {one_arm}: contrastive-only pretraining "
                                       "options; every arm gets these options (the claims compare the objectives): "
                                       "give them under \"pretrain_contrastive\"")
            shared = sorted(set(options) - set(CONTRASTIVE_ONLY_OPTIONS))
            if kind == "pretrain_contrastive" and shared:
                raise BenchConfigError(f"task_options['pretrain_contrastive'] sets {shared}: it takes only the "
                                       f"contrastive objective's own options {list(CONTRASTIVE_ONLY_OPTIONS)}; "
                                       "options both arms have go under \"pretrain\" (every arm gets them)")
        self.world_config()  # refuses unknown fields and bad values now, not at the data stage

    def world_config(self):
        """The synthetic world of the plan's datasets: the preset's WorldConfig with `world` applied."""
        from core.presets import get_preset
        from core.synthetic.config import world_with

        if not isinstance(self.world, dict):
            raise BenchConfigError(f"world must map WorldConfig fields to values, got {self.world!r}")
        try:
            return world_with(get_preset(self.preset), self.world)
        except ValueError as e:
            raise BenchConfigError(f"world: {e}") from None

    def stage_options(self, kind: str, protocol: dict) -> dict:
        """Task options of a stage of `kind` ("pretrain", "occupancy", "detector", "flow_features", "flow_volume"):
        the plan's "mapper" options, then the kind's own (for the contrastive pretraining, `protocol`'s
        objective, also "pretrain_contrastive"), then the benchmark's `protocol` options."""
        own = self.task_options.get(kind, {})
        if kind == "pretrain" and protocol.get("objective") == "contrastive":
            own = {**own, **self.task_options.get("pretrain_contrastive", {})}
        return {**self.task_options.get("mapper", {}), **own, **protocol}

    @property
    def budgets_sorted(self) -> tuple[int | None, ...]:
        """Label budgets, smallest first, `None` (all) last."""
        return tuple(sorted(self.label_budgets, key=lambda b: self.train_episodes + 1 if b is None else b))

    def detector_batch_size(self, budget: int | None, preset_batch_size: int) -> int:
        """Records per step and worker of a detector at `budget`: the run's batch size, no more than one
        worker's share of the labelled records (Ray Train shards them across the workers; every worker
        needs one full batch)."""
        return min(self.batch_size or preset_batch_size, self.budget_records(budget) // max(1, self.workers))

    def budget_records(self, budget: int | None) -> int:
        """How many records a budget labels."""
        return self.train_episodes if budget is None else budget

    def draws_of(self, budget: int | None) -> int:
        """How many disjoint label sets the detector is trained on at `budget`: label_draws at the smallest
        budget unless that is `all` (every record: one set), else 1."""
        return self.label_draws if budget is not None and budget == self.budgets_sorted[0] else 1

    def to_dict(self) -> dict:
        d = asdict(self)
        d["seeds"] = list(self.seeds)
        d["label_budgets"] = ["all" if b is None else b for b in self.label_budgets]
        d["detector_variants"] = [list(v) for v in self.detector_variants]
        d["rules"] = self.rules.to_dict()
        return d

    @staticmethod
    def from_dict(d: dict) -> "BenchConfig":
        """Inverse of to_dict (a seed worker process rebuilds the plan from OUT/work/plan.json)."""
        d = dict(d)
        d["rules"] = StageRules.from_dict(d["rules"])
        d.setdefault("task_options", {})  # plans written before the field
        d.setdefault("label_draws", 1)     # plans written before label draws trained one
        d.setdefault("world", {})          # plans written before the field: the preset's world
        d["label_budgets"] = tuple(None if b == "all" else int(b) for b in d["label_budgets"])
        d["detector_variants"] = tuple(tuple(v) for v in d["detector_variants"])
        d["seeds"] = tuple(d["seeds"])
        return BenchConfig(**d)


# The weight average of the stages that keep one (services/training/weight_average.py): a horizon of
# ~200 steps, the span between two small-preset held-out evaluations.
EMA_DECAY = 0.995


def _plateau(eval_every: int, min_steps: int, max_steps: int, *, ema_decay: float = 0.0) -> StageRule:
    return StageRule(kind="plateau", eval_every=eval_every, patience=3, min_improvement=0.01,
                     min_steps=min_steps, max_steps=max_steps, ema_decay=ema_decay)


def _pretraining(steps: int) -> StageRule:
    """Both pretraining arms: `steps` fixed steps, the bound their plateau rule had. Why not the plateau rule
    (measured in the small report's regeneration, sessions 28-35; docs/findings.md, "The regeneration's
    pretrainings stop unequally"): view regression's held-out loss fell smoothly and ran to the 3000-step
    bound on every seed, while the contrastive one, whose matching term makes it move ±5-10 % between
    evaluations of the same samples, was stopped at 900-1200 steps (selected 600-900) — so the claims
    compared a third of one arm's training with all of the other's. Seed 0's contrastive maps continued to
    3000 steps matched moving voxels better than at its stop (hit / margin 0.365 / +0.217 against
    0.308 / +0.151; regression at 3000 0.346 / +0.188). The paper trains every model for a fixed ~200k
    iterations ("to convergence")."""
    return StageRule.fixed(steps)


def _epochs(epochs: int, min_steps: int, max_steps: int) -> StageRule:
    return StageRule(kind="epochs", epochs=epochs, min_steps=min_steps, max_steps=max_steps)


# Per preset: records, label budgets and stopping rules — the full and the quick profile. The pretrainings train
# a fixed, shared number of steps (`_pretraining`); plateau rules stop on the held-out loss (val_episodes
# records); the detector gets a fixed number of epochs over its
# labelled records (no labelled held-out set: with 2 labels there is none to spare).
# The small detector's floor of 800 steps (40 epochs are 40 steps at 2 labels). 200 had been chosen on fine-tuned
# detectors of an older, narrower model (session 10: seed 0, 16 test records, mAP@0.5 flat from 100 to 200 steps);
# it was short for the frozen-feature ones the few-label claim reads (session 22: both arms pretrained 800 fixed
# steps with the bench's recipe, seeds 0 / 1 / 2, 4 label draws at 2 labels, 32 held-out records of data seed 7,
# never the test set; a lent H100): mean mAP@0.5 contrastive 0.802 / 0.806 / 0.825 at 200 steps, 0.827 / 0.837 /
# 0.869 at 800; regression 0.816 / 0.827 / 0.833, 0.817 / 0.831 / 0.845 — contrastive still gaining 0.025-0.044 on
# every seed, regression 0.001-0.012; the difference moved from -0.014 / -0.021 / -0.008 to +0.010 / +0.006 /
# +0.024 (per-draw sd 0.024-0.044). From 800 to 1600 (session 23: this report's own seed-0 pretrainings, draws 0
# and 1, the same held-out records, CPU): frozen contrastive 0.795 -> 0.811 / 0.860 -> 0.854, frozen regression
# 0.765 -> 0.773 / 0.844 -> 0.846 — each within the claims' 0.02 margin, their mean difference +0.023 at both
# lengths, so 800 is long enough for them. The detector trained from random initialisation gains on one draw and
# not the other (0.439 / 0.580 / 0.589 / 0.648 / 0.681 and 0.690 / 0.672 / 0.689 / 0.694 / 0.695 at 100 / 200 /
# 400 / 800 / 1600 steps; mean +0.017 from 800 to 1600, within the margin but not settled): its row may be a
# little low, and it is 0.09 below regression even at 1600 on draw 0; doubling the floor for it would cost each
# seed ~2 h here. The fine-tuned contrastive detector: 0.666 / 0.622 / 0.771 / 0.785 at 100-800 (draw 0). The protocol of `tests/benchmarks/bench_label_draws.py [--pretrain-steps 800] [--frozen] --draws ...
# --detector-steps 200 800 [1600]` (each longer detector continues the shorter one: constant learning rate,
# seeded per step, so the same as training it from the start at 2 labels).
_PROFILES: dict[tuple[str, bool], dict] = {
    # tiny keeps one label draw (its report is the quick-to-regenerate one; the draws are small's measured need).
    ("tiny", False): dict(train_episodes=48, val_episodes=8, test_episodes=16, label_budgets=(2, 8, None),
                          rules=StageRules(pretrain=_pretraining(1500), detector=_epochs(40, 30, 1000),
                                           flow=_plateau(50, 100, 1000),
                                           egomotion=_plateau(50, 100, 1000, ema_decay=EMA_DECAY),
                                           occupancy=_plateau(50, 100, 1000, ema_decay=EMA_DECAY))),
    # 64 test records (32 static- and 32 moving-camera pairs): on 16 the verdicts rested on 8 pairs per camera
    # setting, and the small report's verdicts changed on 64 (egomotion's rotation 1.09-1.17 x ICP's on the 16
    # records' 8 pairs, 1.49-1.73 x on the 64 records' 32). Only evaluations read them (~4x their time).
    # Egomotion and occupancy keep a weight average (EMA 0.995) and egomotion trains at least 1000 steps. Measured
    # (session 15; 3 seeds, checkpoints every 250 steps, on 32 held-out moving-camera pairs / 16 held-out records
    # of `data generate --seed 7`, never the test set; trained on a lent H100): the average's held-out
    # criterion was lower than the last step's weights' at 18 of 21 checkpoints, and the occupancy module's
    # worse class accuracy at the validation-balanced threshold was 0.953-0.966 at every checkpoint from step
    # 500 with the average (0.939-0.961 without). Egomotion's rotation error kept falling with steps
    # (0.106-0.111 deg at 250, 0.099-0.106 at 750; the old rule kept step 300 on seed 1).
    # Four label draws at 2 labels (session 17): the bench's three seeds' fine-tuned contrastive and regression
    # detectors, each trained on 8 disjoint pairs of training records and scored on 32 held-out records of `data
    # generate --seed 7` (never the test set; a lent H100), gave mAP@0.5 from 0.45 to 0.93 by draw, and the
    # contrastive - regression difference a per-draw spread (sd) of 0.026 / 0.055 / 0.035 by seed, against the
    # claim's margin of 0.02. With 4 draws the spread of the mean is halved.
    ("small", False): dict(train_episodes=64, val_episodes=8, test_episodes=64, label_budgets=(2, 8, None),
                           label_draws=4, detector_variants=JUDGED_VARIANTS,
                           rules=StageRules(pretrain=_pretraining(3000), detector=_epochs(40, 800, 2000),
                                            flow=_plateau(100, 200, 2000),
                                            egomotion=_plateau(100, 1000, 3000, ema_decay=EMA_DECAY),
                                            occupancy=_plateau(200, 400, 4000, ema_decay=EMA_DECAY))),
    ("paper", False): dict(train_episodes=1024, val_episodes=32, test_episodes=100,
                           label_budgets=(8, 32, 128, 512, None), label_draws=4,
                           rules=StageRules(pretrain=_pretraining(200_000),
                                            detector=_epochs(40, 500, 20_000), flow=_plateau(1000, 5000, 50_000),
                                            egomotion=_plateau(1000, 5000, 50_000, ema_decay=EMA_DECAY),
                                            occupancy=_plateau(1000, 5000, 50_000, ema_decay=EMA_DECAY))),
}
_QUICK = dict(train_episodes=4, val_episodes=2, test_episodes=2, label_budgets=(2, None), label_draws=2,
              rules=StageRules(pretrain=StageRule.fixed(2), detector=StageRule.fixed(2), flow=StageRule.fixed(2),
                               # the weight average as in the full plans, so the quick profile runs its path
                               egomotion=StageRule.fixed(2, ema_decay=EMA_DECAY),
                               occupancy=StageRule.fixed(2, ema_decay=EMA_DECAY)), retrieval_per_example=4,
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


def with_steps(config: BenchConfig, **steps: int) -> BenchConfig:
    """`config` with some stages trained for a fixed number of steps (pretrain=, detector=, flow=,
    egomotion=, occupancy=) instead of their stopping rule."""
    for name, value in steps.items():
        if name not in STAGE_NAMES:
            raise BenchConfigError(f"no training stage {name!r}; choose from {STAGE_NAMES}")
        if value < 1:
            raise BenchConfigError(f"steps of stage {name!r} must be >= 1, got {value}")
    # the length changes; the weight average, part of how the stage makes its weights, stays
    return replace(config, rules=replace(config.rules, **{
        k: StageRule.fixed(v, ema_decay=getattr(config.rules, k).ema_decay) for k, v in steps.items()}))
