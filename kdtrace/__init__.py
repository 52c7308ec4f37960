"""kdtrace: CPU Monte Carlo path tracing on naive and local-branch SAH KD-trees."""

from kdtrace.config import DEFAULT_CONFIG, Config, load_config
from kdtrace.scene import Camera, Material, Scene, Sky

__all__ = ["Camera", "Config", "DEFAULT_CONFIG", "Material", "Scene", "Sky", "load_config"]
