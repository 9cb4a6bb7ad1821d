"""The built-in synthetic RGB-D world: procedural urban-like scenes rendered by ray casting in torch.

`generate_record(preset, seed=...)` returns one record (docs/data.md#records); `WorldConfig` holds the world's
knobs and `default_world_config(preset)` the defaults per preset.
"""

from core.synthetic.config import WorldConfig, default_world_config
from core.synthetic.generate import generate_record

__all__ = ["WorldConfig", "default_world_config", "generate_record"]
