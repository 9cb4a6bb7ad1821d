"""argparse `type=` functions for numbers with a valid range: a bad value is a one-line usage error
naming the option (`n3dmap serve: error: argument --http-port: ...`, exit 2) before anything starts."""

from __future__ import annotations

import argparse
import math

# Seconds per sequence number of frames without timestamps (`--frame-dt` of `serve` and `stream bridge`):
# = core.pipeline.moving_boxes.DEFAULT_DT (a test keeps them equal); not imported, so that parsing the
# command line does not load torch.
DEFAULT_FRAME_DT = 0.2
# m/s under which a component of moving voxels is no moving object (`--min-object-speed` of `stream bridge`):
# = core.pipeline.moving_boxes.MovingObjectsConfig.min_object_speed (the same test keeps them equal).
DEFAULT_MIN_OBJECT_SPEED = 1.0
FRAME_DT_HELP = ("seconds between consecutive frames of a camera, used only for moving-object pairs whose frames "
                 "carry neither capture times nor timestamps (all 0): the pair then spans (sequence1 − sequence0) "
                 "× S. Otherwise the interval is the frames' capture-time difference when both carry one, else "
                 "their timestamp difference (default %(default)s, the synthetic world's step)")


def _number(text: str, kind: type, what: str):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
    if isinstance(value, float) and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
    return value


def positive_int(text: str) -> int:
    value = _number(text, int, "an integer ≥ 1")
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def non_negative_int(text: str) -> int:
    value = _number(text, int, "an integer ≥ 0")
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be ≥ 0, got {value}")
    return value


def positive_float(text: str) -> float:
    value = _number(text, float, "a number > 0")
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def non_negative_float(text: str) -> float:
    value = _number(text, float, "a number ≥ 0")
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"must be ≥ 0, got {text}")
    return value


def unit_fraction(text: str) -> float:
    """A number in (0, 1]."""
    value = _number(text, float, "a number in (0, 1]")
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"must be in (0, 1], got {text}")
    return value


# = services.inference.validation.MIN_PAIR_INTERVAL_S (a test keeps them equal): the shortest interval a pair
# of frames may span, so that velocities (displacement / interval) stay finite.
MIN_INTERVAL_S = 1e-4


def frame_interval(text: str) -> float:
    """Seconds between frames (--frame-dt, --capture-dt), at least MIN_INTERVAL_S: a pair over a shorter
    interval is refused (its velocities would overflow), so such a setting would refuse every frame."""
    value = _number(text, float, f"a number of seconds ≥ {MIN_INTERVAL_S:g}")
    if not value >= MIN_INTERVAL_S:
        raise argparse.ArgumentTypeError(f"must be at least {MIN_INTERVAL_S:g} s, got {text}")
    return value


def saliency_score(text: str) -> float:
    """A moving-object score threshold in [−1, 1] (the centre-surround saliency the boxes are scored by)."""
    value = _number(text, float, "a number in [-1, 1]")
    if not -1.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [-1, 1], got {text}")
    return value


MIN_RATE_HZ, MAX_RATE_HZ = 1e-3, 1000.0


def frame_rate(text: str) -> float:
    """Frames per second in [0.001, 1000]: one frame in 1000 s at the slowest (a rate of 1e-300 waited 1e300 s,
    which sleep() refuses with an OverflowError), and above 1000 Hz the render, not the rate, paces it."""
    value = _number(text, float, f"a number in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}]")
    if not MIN_RATE_HZ <= value <= MAX_RATE_HZ:
        raise argparse.ArgumentTypeError(f"must be in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}] Hz, got {text}")
    return value


def port(text: str) -> int:
    """A TCP port, 0..65535 (0: the OS picks a free one)."""
    value = _number(text, int, "a port number (0-65535)")
    if not 0 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port number 0-65535, got {value}")
    return value
