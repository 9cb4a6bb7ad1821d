"""Typed errors of the core library. Services turn them into one-line CLI messages or 4xx replies."""


class N3dmapError(Exception):
    """Base of every error n3dmap raises on purpose (bad input, bad data, bad config)."""


class DataError(N3dmapError):
    """A dataset, shard or record is missing, corrupt or does not match the data contract."""


class ShapeError(N3dmapError, ValueError):
    """A tensor's shape or dtype is not what a public function expects."""


class ConfigError(N3dmapError, ValueError):
    """An option or config value is unknown or out of range (a preset name, a view index, a rate)."""


class BundleError(N3dmapError):
    """A model bundle is missing, corrupt or lacks a module."""


def check_shape(name: str, t, expected: tuple) -> None:
    """Raise ShapeError unless `t.shape` matches `expected` (None entries match anything)."""
    shape = tuple(t.shape)
    if len(shape) != len(expected) or any(e is not None and e != s for e, s in zip(expected, shape)):
        want = "×".join("?" if e is None else str(e) for e in expected)
        raise ShapeError(f"{name}: expected shape {want}, got {'×'.join(map(str, shape)) or 'scalar'}")
