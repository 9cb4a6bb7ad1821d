"""The strict judge of the paper benchmark: a claim holds only when every seed shows it, by a floor.

A claim is a list of *conditions*, each checked on every seed on its own (seeds are paired: the
contrastive and the regression model of seed 2 are compared with each other, never with another
seed's). A condition says how one seed's numbers must relate:

- `Better(a, b, floor)`: a beats b by at least `floor.margin` (in the metric's direction);
- `Positive(x, floor)`: a derived gain x is at least `floor.margin` (a "gain" claim needs the gain
  itself to be positive, not only larger than another gain);
- `AtLeast(a, target)` / `RatioAtMost(a, b, ratio)` / `WithinOf(a, b, tolerance)`: absolute targets
  (the paper's occupancy accuracy, egomotion as a ratio of ICP's errors); a target is its own floor.

Each (condition, seed) gives one outcome: "agree" (shows the paper's direction by the floor),
"disagree" (does not: the wrong direction, or the right one by less than the floor), "vacuous" (both
sides sit below the metric's floor of meaning, e.g. two APs under 0.05: nothing is being compared)
or "missing" (a number was not produced). The verdict, in this order:

1. quick profile: no verdict at all (`holds` None, "not judged");
2. any seed disagreeing: "does not hold" — every seed must agree, so one seed that shows the other
   direction settles it whatever the other seeds lack;
3. a missing number, or fewer than `MIN_SEEDS` seeds: "undetermined";
4. any seed vacuous: "undetermined" (for `ControlFails`: an untrained control meets the claim too, so it does
   not test training; for `Unsaturated`: the values it needs room above are at the ceiling);
5. otherwise (every seed agrees): "holds".

Nothing here is tuned to make a claim hold: floors are fixed per metric family and printed in the
report (`FLOORS`).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from typing import Callable, Mapping

MIN_SEEDS = 3
# Every comparison allows this much float round-off at its limit (|0.3 − 0.4| is 0.10000000000000003 > 0.1).
ROUNDING = 1e-12
HOLDS, FAILS, UNDETERMINED, NOT_JUDGED = "holds", "does not hold", "undetermined", "not judged"


@dataclass(frozen=True)
class Floor:
    """The least difference that shows a direction, and the level below which a value means nothing."""

    name: str
    margin: float
    meaning: float | None = None      # both sides below it: the comparison is vacuous (None: never)
    lower_is_better: bool = False


FLOORS: dict[str, Floor] = {
    "ap": Floor("AP, mAP and P@K", margin=0.02, meaning=0.05),
    # A difference of two APs (a gain): the AP margin, but no floor of meaning of its own (whether the
    # APs behind it mean anything is checked by the condition that the gain is positive).
    "gain": Floor("AP gain (difference of two APs)", margin=0.02),
    "epe": Floor("flow L1 EPE (voxels)", margin=0.05, lower_is_better=True),
}


SeedValues = Mapping[str, float | None]   # value name -> this seed's number


@dataclass(frozen=True)
class Better:
    """Seed by seed: value `a` beats value `b` by at least the floor's margin."""

    a: str
    b: str
    floor: Floor

    def text(self) -> str:
        word = "<" if self.floor.lower_is_better else ">"
        return f"{self.a} {word} {self.b} by ≥ {self.floor.margin:g}"

    def outcome(self, v: SeedValues) -> str:
        a, b = v.get(self.a), v.get(self.b)
        if not _finite(a, b):
            return "missing"
        if _below_meaning(self.floor, a, b):
            return "vacuous"        # a gap between two meaningless numbers is no evidence either way
        gain = (b - a) if self.floor.lower_is_better else (a - b)
        return "agree" if gain >= self.floor.margin - ROUNDING else "disagree"


@dataclass(frozen=True)
class Positive:
    """Seed by seed: the derived value `x` (a gain) is at least the floor's margin."""

    x: str
    floor: Floor
    of: tuple[str, ...] = ()          # the values x is derived from (for the floor of meaning)

    def text(self) -> str:
        return f"{self.x} ≥ {self.floor.margin:g}"

    def outcome(self, v: SeedValues) -> str:
        x = v.get(self.x)
        if not _finite(x) or not _finite(*(v.get(n) for n in self.of)):
            return "missing"
        if self.of and _below_meaning(self.floor, *(v[n] for n in self.of)):
            return "vacuous"
        return "agree" if x >= self.floor.margin - ROUNDING else "disagree"


@dataclass(frozen=True)
class AtLeast:
    """Seed by seed: `a` ≥ `target` (an absolute target such as the paper's occupancy accuracy)."""

    a: str
    target: float

    def text(self) -> str:
        return f"{self.a} ≥ {self.target:g}"

    def outcome(self, v: SeedValues) -> str:
        a = v.get(self.a)
        if not _finite(a):
            return "missing"
        return "agree" if a >= self.target - ROUNDING else "disagree"


@dataclass(frozen=True)
class RatioAtMost:
    """Seed by seed: `a` ≤ `ratio` × `b` (errors: the model against a baseline)."""

    a: str
    b: str
    ratio: float

    def text(self) -> str:
        return f"{self.a} ≤ {self.ratio:g} × {self.b}"

    def outcome(self, v: SeedValues) -> str:
        a, b = v.get(self.a), v.get(self.b)
        if not _finite(a, b):
            return "missing"
        return "agree" if a <= self.ratio * b + ROUNDING else "disagree"


@dataclass(frozen=True)
class WithinOf:
    """Seed by seed: |a − b| ≤ tolerance, with `a` or `b` above the floor of meaning."""

    a: str
    b: str
    tolerance: float
    floor: Floor

    def text(self) -> str:
        return f"|{self.a} − {self.b}| ≤ {self.tolerance:g}"

    def outcome(self, v: SeedValues) -> str:
        a, b = v.get(self.a), v.get(self.b)
        if not _finite(a, b):
            return "missing"
        if _below_meaning(self.floor, a, b):
            return "vacuous"        # two zeros are "within 0.1" of each other and say nothing
        return "agree" if abs(a - b) <= self.tolerance + ROUNDING else "disagree"


@dataclass(frozen=True)
class ControlFails:
    """Seed by seed: a control (an untrained module) does not also meet every one of `conditions`, read with each
    name of `control` standing in for the name it maps from. When it does, the conditions do not test what
    training brings: "vacuous" (the egomotion module's weightless last stage reached ICP untrained)."""

    conditions: tuple
    control: tuple[tuple[str, str], ...]   # (name, the control's name for it)

    def text(self) -> str:
        return f"the control ({', '.join(c for _, c in self.control)}) does not also meet them"

    def outcome(self, v: SeedValues) -> str:
        swapped = {**v, **{name: v.get(control) for name, control in self.control}}
        outcomes = [c.outcome(swapped) for c in self.conditions]
        if "missing" in outcomes:
            return "missing"
        return "vacuous" if all(o == "agree" for o in outcomes) else "agree"


@dataclass(frozen=True)
class Unsaturated:
    """Seed by seed: not every one of `names` sits at or above `ceiling`. When all do, a comparison that needs room
    above them cannot be made: "vacuous" (detectors at mAP ≥ 0.98 with all labels leave the gain there ~0 by
    construction, so "the gain is largest at few labels" would follow from the gain at few labels alone)."""

    names: tuple[str, ...]
    ceiling: float

    def text(self) -> str:
        return f"not all of {', '.join(self.names)} ≥ {self.ceiling:g} (saturated)"

    def outcome(self, v: SeedValues) -> str:
        values = [v.get(n) for n in self.names]
        if not _finite(*values):
            return "missing"
        return "vacuous" if all(x >= self.ceiling - ROUNDING for x in values) else "agree"


Condition = Better | Positive | AtLeast | RatioAtMost | WithinOf | ControlFails | Unsaturated


@dataclass(frozen=True)
class Verdict:
    holds: bool | None                # True / False / None (undetermined or not judged)
    verdict: str                      # HOLDS | FAILS | UNDETERMINED | NOT_JUDGED
    reason: str
    outcomes: dict                    # seed -> [outcome per condition]


def judge(conditions: list[Condition], per_seed: Mapping[str, SeedValues], *, quick: bool = False,
          min_seeds: int = MIN_SEEDS) -> Verdict:
    """The verdict of one claim; `per_seed` maps each seed to its named values (module docstring)."""
    outcomes = {seed: [c.outcome(values) for c in conditions] for seed, values in per_seed.items()}
    if quick:
        return Verdict(None, NOT_JUDGED, "quick profile: its few steps say nothing about the paper", outcomes)
    failing = {i: sorted((s for s, row in outcomes.items() if row[i] == "disagree"), key=seed_key)
               for i in range(len(conditions))}
    if any(failing.values()):   # per condition, the seeds that fail it
        return Verdict(False, FAILS, "; ".join(f"seed(s) {', '.join(seeds)} fail '{conditions[i].text()}'"
                                               for i, seeds in failing.items() if seeds), outcomes)
    missing = [(s, c) for s, row in outcomes.items() for c, o in zip(conditions, row) if o == "missing"]
    if missing:
        s, c = missing[0]
        return Verdict(None, UNDETERMINED, f"seed {s} lacks a number for '{c.text()}'", outcomes)
    if len(per_seed) < min_seeds:
        return Verdict(None, UNDETERMINED, f"{len(per_seed)} seed(s); a verdict needs at least {min_seeds}",
                       outcomes)
    vacuous = [(s, c) for s, row in outcomes.items() for c, o in zip(conditions, row) if o == "vacuous"]
    if vacuous:
        s, c = vacuous[0]
        if isinstance(c, Unsaturated):
            return Verdict(None, UNDETERMINED, f"seed {s}: {', '.join(c.names)} all ≥ {c.ceiling:g}, saturated: "
                           "nothing is left to compare there", outcomes)
        if isinstance(c, ControlFails):
            return Verdict(None, UNDETERMINED, f"seed {s}: the untrained control meets the claim too, so it does "
                           "not test what training brings", outcomes)
        return Verdict(None, UNDETERMINED, f"seed {s}: both sides of '{c.text()}' lie below the floor of "
                       "meaning", outcomes)
    return Verdict(True, HOLDS, f"all {len(per_seed)} seeds agree", outcomes)


def derive(per_seed: Mapping[str, dict], name: str, fn: Callable[..., float], *args: str) -> None:
    """Add value `name` = fn(values of `args`) to every seed (None where an input is missing)."""
    for values in per_seed.values():
        inputs = [values.get(a) for a in args]
        values[name] = fn(*inputs) if _finite(*inputs) else None


def _finite(*values) -> bool:
    """Every value a finite real number (numpy scalars too; a bool is no number here)."""
    return all(isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v) for v in values)


def _below_meaning(floor: Floor, *values: float) -> bool:
    return floor.meaning is not None and all(v < floor.meaning for v in values)


def seed_key(seed: str):
    return (0, int(seed)) if str(seed).isdigit() else (1, str(seed))
