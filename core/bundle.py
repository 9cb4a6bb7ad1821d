"""Model bundles: a directory with `bundle.json` and `weights.safetensors`, loaded without unpickling.

bundle.json:
    format_version   int (BUNDLE_FORMAT_VERSION)
    n3dmap_version   str
    preset           Preset.to_dict()
    grid             GridConfig.to_dict() (the preset's grid, repeated for readers that need only it)
    modules          {name: {"kind": registry kind, "config": constructor kwargs, "params": count}}
    provenance       free dict (task, objective, run id, steps, parent bundles, …)
    metrics          free dict of final metrics
weights.safetensors: every module's state_dict (parameters and buffers) under "<name>.<key>".

Later jobs `load_bundle` an initialising bundle, add modules and save the union with `save_bundle`
(`merged_modules` keeps the parent's provenance under "parents"). `merge_bundles` joins bundles trained
apart (e.g. a benchmark's flow and egomotion stages) into one to serve (`n3dmap bundle merge`).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping, Sequence

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file
from torch import nn

import core
from core.errors import BundleError
from core.models.registry import build_module, kind_of
from core.presets import Preset

BUNDLE_FORMAT_VERSION = 1
BUNDLE_JSON = "bundle.json"
WEIGHTS_FILE = "weights.safetensors"


@dataclass
class Bundle:
    """A loaded bundle: the preset, named modules in eval mode on one device, and bundle.json as `meta`."""

    preset: Preset
    modules: dict[str, nn.Module]
    meta: dict = field(default_factory=dict)
    path: str | None = None

    def require(self, name: str) -> nn.Module:
        """The module called `name`; BundleError naming what the bundle holds otherwise."""
        try:
            return self.modules[name]
        except KeyError:
            raise BundleError(f"bundle {self.path or ''} has no module {name!r}; it holds "
                              f"{sorted(self.modules)}") from None

    @property
    def device(self) -> torch.device:
        for m in self.modules.values():
            for p in m.parameters():
                return p.device
        return torch.device("cpu")

    @property
    def version(self) -> str:
        """A short identity for responses: '<format>/<n3dmap version>/<run id or dir name>'."""
        run = self.meta.get("provenance", {}).get("run_id") or (Path(self.path).name if self.path else "?")
        return f"{self.meta.get('format_version')}/{self.meta.get('n3dmap_version')}/{run}"


def _jsonable(value):
    """Metrics/provenance to plain JSON (tensors -> numbers, non-finite floats -> strings)."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu().tolist()
    if isinstance(value, dict):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if hasattr(value, "item") and callable(value.item):  # numpy scalars
        return _jsonable(value.item())
    return value


def save_bundle(directory: str | os.PathLike, *, modules: dict[str, nn.Module], preset: Preset,
                provenance: dict | None = None, metrics: dict | None = None) -> Path:
    """Write `bundle.json` + `weights.safetensors` into `directory` (created if needed). Returns the path.

    Every module must be of a kind registered in core.models.registry. Files are written to temporary
    names and renamed, so a crash never leaves a half-written bundle under the final names.
    """
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    tensors: dict[str, torch.Tensor] = {}
    entries: dict[str, dict] = {}
    for name, module in modules.items():
        if "." in name or not name:
            raise BundleError(f"module name {name!r} must be non-empty and contain no '.'")
        module = getattr(module, "module", module)  # unwrap DDP
        entries[name] = {"kind": kind_of(module), "config": module.config(),
                         "params": int(sum(p.numel() for p in module.parameters()))}
        for key, value in module.state_dict().items():
            tensors[f"{name}.{key}"] = value.detach().cpu().contiguous()
    meta = {"format_version": BUNDLE_FORMAT_VERSION, "n3dmap_version": core.__version__,
            "preset": preset.to_dict(), "grid": preset.grid.to_dict(), "modules": entries,
            "provenance": _jsonable(provenance or {}), "metrics": _jsonable(metrics or {})}
    tmp_weights, tmp_json = out / (WEIGHTS_FILE + ".tmp"), out / (BUNDLE_JSON + ".tmp")
    save_file(tensors, str(tmp_weights), metadata={"format_version": str(BUNDLE_FORMAT_VERSION)})
    tmp_json.write_text(json.dumps(meta, indent=2, sort_keys=True))
    os.replace(tmp_weights, out / WEIGHTS_FILE)
    os.replace(tmp_json, out / BUNDLE_JSON)
    return out


def read_bundle_meta(directory: str | os.PathLike) -> dict:
    """Parse and check `bundle.json` only (no weights): for `n3dmap bundle info`."""
    path = Path(directory) / BUNDLE_JSON
    if not path.is_file():
        raise BundleError(f"not a bundle: {path} is missing")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise BundleError(f"corrupt {path}: {e}") from None
    if not isinstance(meta, dict):
        raise BundleError(f"corrupt {path}: not a JSON object")
    for key in ("format_version", "preset", "modules"):
        if key not in meta:
            raise BundleError(f"corrupt {path}: missing key {key!r}")
    if meta["format_version"] != BUNDLE_FORMAT_VERSION:   # first: another version may lay out its modules otherwise
        raise BundleError(f"{path}: format_version {meta['format_version']} not supported "
                          f"(this n3dmap reads {BUNDLE_FORMAT_VERSION})")
    modules = meta["modules"]
    if not isinstance(modules, dict):
        raise BundleError(f"corrupt {path}: 'modules' must map a module name to its kind and config, "
                          f"got {type(modules).__name__}")
    for name, entry in modules.items():
        if not (isinstance(entry, dict) and isinstance(entry.get("kind"), str)
                and isinstance(entry.get("config"), dict)):
            raise BundleError(f"corrupt {path}: module {name!r} needs a 'kind' (string) and a 'config' (object)")
    return meta


def load_bundle(directory: str | os.PathLike, device: torch.device | str = "cpu", *,
                only: list[str] | None = None) -> Bundle:
    """Load a bundle's modules (all, or those named in `only`) onto `device`, in eval mode.

    BundleError if bundle.json or the weights file is missing or corrupt, a requested module is absent,
    or a stored tensor is missing or has the wrong shape.
    """
    directory = Path(directory)
    meta = read_bundle_meta(directory)
    weights_path = directory / WEIGHTS_FILE
    if not weights_path.is_file():
        raise BundleError(f"bundle {directory}: {WEIGHTS_FILE} is missing")
    try:
        tensors = load_file(str(weights_path), device="cpu")
    except (SafetensorError, OSError, ValueError) as e:
        raise BundleError(f"bundle {directory}: cannot read {WEIGHTS_FILE}: {e}") from None
    try:
        preset = Preset.from_dict(meta["preset"])
    except (KeyError, TypeError, ValueError) as e:
        raise BundleError(f"bundle {directory}: bad preset in {BUNDLE_JSON}: {e}") from None
    names = list(meta["modules"]) if only is None else list(only)
    modules: dict[str, nn.Module] = {}
    for name in names:
        if name not in meta["modules"]:
            raise BundleError(f"bundle {directory} has no module {name!r}; it holds {sorted(meta['modules'])}")
        entry = meta["modules"][name]
        try:
            module = build_module(entry["kind"], entry["config"])
        except (BundleError, ValueError, KeyError) as e:
            raise BundleError(f"bundle {directory}: module {name!r} in {BUNDLE_JSON}: {e}") from None
        expected = module.state_dict()
        state = {}
        for key, ref in expected.items():
            stored = tensors.get(f"{name}.{key}")
            if stored is None:
                raise BundleError(f"bundle {directory}: weights lack {name}.{key}")
            if stored.shape != ref.shape:
                raise BundleError(f"bundle {directory}: {name}.{key} has shape {tuple(stored.shape)}, "
                                  f"module expects {tuple(ref.shape)}")
            state[key] = stored
        module.load_state_dict(state, strict=True)
        modules[name] = module.to(device).eval()
    return Bundle(preset=preset, modules=modules, meta=meta, path=str(directory))


def merged_modules(parent: Bundle, new: dict[str, nn.Module], *, replace: bool = False) -> dict[str, nn.Module]:
    """The parent's modules plus `new` (for a job that initialised from `parent` and adds modules).

    A name in both raises BundleError unless `replace` (e.g. a fine-tuned mapper).
    """
    clash = sorted(set(parent.modules) & set(new))
    if clash and not replace:
        raise BundleError(f"modules {clash} already in the parent bundle; pass replace=True to overwrite")
    return {**parent.modules, **new}


def parent_provenance(parent: Bundle) -> dict:
    """Provenance entry describing `parent`, for the child's provenance["parents"] list."""
    return {"path": parent.path, "version": parent.version, "provenance": parent.meta.get("provenance", {})}


# Module kinds that read the mapper's features: such a module is only meaningful beside the mapper it was
# trained on. (egomotion reads the fused input volumes; flow reads features only with inputs="features".)
MAPPER_READER_KINDS = ("projector", "net2d", "occupancy_head", "detector3d")


def reads_mapper(entry: dict) -> bool:
    """Whether a bundle.json module entry ({"kind", "config"}) reads the mapper's feature maps."""
    kind, config = entry.get("kind"), entry.get("config") or {}
    return kind in MAPPER_READER_KINDS or (kind == "flow3d" and config.get("inputs") == "features")


def same_module(a: nn.Module, b: nn.Module) -> bool:
    """Same registered kind, constructor config and every state tensor bit for bit."""
    if kind_of(a) != kind_of(b) or a.config() != b.config():
        return False
    sa, sb = a.state_dict(), b.state_dict()
    # torch.equal is False for other shapes; the dtype is compared apart since it compares values only.
    return sa.keys() == sb.keys() and all(sa[k].dtype == sb[k].dtype and torch.equal(sa[k].cpu(), sb[k].cpu()) for k in sa)


def merge_bundles(bundles: Sequence[Bundle], *, take: Mapping[str, int] | None = None,
                  ) -> tuple[dict[str, nn.Module], dict[str, int]]:
    """The union of several bundles' modules: ({name: module}, {name: index in `bundles` it came from}).

    All bundles must share one preset (grid, widths). A name held by several bundles is taken once, from the
    first, when every copy is the same module bit for bit (`same_module`); where copies differ, `take[name]`
    (an index into `bundles`) must say which — never silently the first: an occupancy head or a flow module
    over features reads the mapper it was trained on. `take` may also pick among equal copies. BundleError
    names the bundles and modules otherwise.
    """
    take = take or {}
    if len(bundles) < 2:
        raise BundleError(f"merging needs at least two bundles, got {len(bundles)}")
    first = bundles[0]
    for b in bundles[1:]:
        if b.preset.to_dict() != first.preset.to_dict():
            raise BundleError(f"bundles {first.path} (preset {first.preset.name}) and {b.path} (preset "
                              f"{b.preset.name}) have different presets; only bundles of one preset merge")
    holders: dict[str, list[int]] = {}
    for i, b in enumerate(bundles):
        for name in b.modules:
            holders.setdefault(name, []).append(i)
    for name, index in take.items():
        if name not in holders:
            raise BundleError(f"--take {name}: no bundle holds a module {name!r}; they hold {sorted(holders)}")
        if index not in holders[name]:
            raise BundleError(f"--take {name}: bundle {bundles[index].path if 0 <= index < len(bundles) else index} "
                              f"has no module {name!r}; it is in {[bundles[i].path for i in holders[name]]}")
    modules: dict[str, nn.Module] = {}
    sources: dict[str, int] = {}
    for name, indices in holders.items():
        if name in take:
            source = take[name]
        else:
            differ = [i for i in indices[1:] if not same_module(bundles[indices[0]].modules[name], bundles[i].modules[name])]
            if differ:
                raise BundleError(f"module {name!r} differs between {[bundles[i].path for i in indices]}; say which "
                                  f"to keep with --take {name}=B (the modules that read a mapper need the one "
                                  "they were trained on)")
            source = indices[0]
        modules[name], sources[name] = bundles[source].modules[name], source
    return modules, sources


def foreign_mapper_readers(bundles: Sequence[Bundle], sources: Mapping[str, int]) -> list[str]:
    """Modules of a merge that read a mapper (`reads_mapper`) but come from a bundle whose own mapper was
    not the one kept and differs from it: they will read features they were not trained on."""
    if "mapper" not in sources:
        return []
    kept = bundles[sources["mapper"]].modules["mapper"]
    foreign = []
    for name, index in sources.items():
        own = bundles[index].modules.get("mapper")
        if name != "mapper" and reads_mapper(bundles[index].meta.get("modules", {}).get(name, {})) \
                and own is not None and own is not kept and not same_module(own, kept):
            foreign.append(name)
    return sorted(foreign)
