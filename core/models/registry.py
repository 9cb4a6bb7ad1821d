"""Module kinds a bundle can hold: kind name -> class, and `build_module(kind, config)`.

The table lists "package.module:Class" so each kind is one greppable line and importing the
registry does not import every model. Other parts add their kinds here (egomotion, flow, detector).
Every registered class takes keyword-only constructor arguments and has `config()` returning them.
"""

from __future__ import annotations

import importlib

from torch import nn

from core.errors import BundleError

MODULE_KINDS: dict[str, str] = {
    "encoder3d": "core.models.encoder3d:Encoder3D",
    "mapper": "core.models.latent_map:Mapper",
    "projector": "core.models.projector:Projector",
    "net2d": "core.models.net2d:Net2D",
    "occupancy_head": "core.models.occupancy_head:OccupancyHead",
    "egomotion": "core.models.egomotion:EgomotionNet",
    "flow3d": "core.models.flow3d:Flow3D",
    "detector3d": "core.models.detector3d:Detector3D",
}


def module_class(kind: str) -> type[nn.Module]:
    """The class registered under `kind`; BundleError naming the known kinds otherwise."""
    try:
        path = MODULE_KINDS[kind]
    except KeyError:
        raise BundleError(f"unknown module kind {kind!r}; known kinds: {sorted(MODULE_KINDS)}") from None
    module_name, class_name = path.split(":")
    return getattr(importlib.import_module(module_name), class_name)


def kind_of(module: nn.Module) -> str:
    """The registered kind of `module`'s class; BundleError if the class is not registered."""
    cls = type(module)
    for kind, path in MODULE_KINDS.items():
        module_name, class_name = path.split(":")
        if cls.__module__ == module_name and cls.__name__ == class_name:
            return kind
    raise BundleError(f"module class {cls.__module__}.{cls.__name__} is not registered in "
                      "core.models.registry.MODULE_KINDS")


def build_module(kind: str, config: dict) -> nn.Module:
    """Rebuild a module from its kind and `config()` dict."""
    cls = module_class(kind)
    try:
        return cls(**config)
    except TypeError as e:
        raise BundleError(f"cannot build module kind {kind!r} from config {config}: {e}") from None
