"""kdtrace: CPU Monte Carlo path tracing on naive and local-branch SAH KD-trees.

How to use::

    from kdtrace import load_scene, build_kdtree
    scene = load_scene("cbox-sphere")            # a scene name from scenes/, or a .toml/.obj/.ply path
    tree = build_kdtree(scene, variant="local")  # or "naive"
    t, tri, u, v = tree.intersect(origins, directions)
"""

from kdtrace.config import DEFAULT_CONFIG, Config, load_config
from kdtrace.kdtree import KDTree, build_kdtree
from kdtrace.render import RenderResult, render, render_stereo
from kdtrace.scene import Camera, Material, Scene, Sky
from kdtrace.scenes import list_scenes, load_scene

__all__ = [
    "Camera", "Config", "DEFAULT_CONFIG", "KDTree", "Material", "Scene", "Sky",
    "RenderResult", "build_kdtree", "list_scenes", "load_config", "load_scene", "render", "render_stereo",
]
