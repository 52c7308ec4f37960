"""Resolved configuration: frozen dataclasses built from ``defaults.toml``.

Every tunable of kdtrace lives in ``kdtrace/defaults.toml``; this module turns that
file (optionally overlaid with a user TOML file) into immutable dataclasses, so a
result file can record exactly the configuration that produced it.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DEFAULTS_PATH = Path(__file__).with_name("defaults.toml")


@dataclass(frozen=True)
class KDTreeConfig:
    """Build parameters of both SAH KD-trees (paper §2, eq. 1 and Terminate).

    Attributes
    ----------
    traversal_cost : float
        K_T, cost of one traversal step (arbitrary unit).
    intersection_cost : float
        K_I, cost of one ray-triangle test (same unit).
    min_leaf_size : int
        Nodes with this many triangles or fewer are not split.
    depth_base, depth_log_factor : float
        Depth limit ``depth_base + depth_log_factor * log2(N)``.
    axis_selection : str
        ``"all"`` (best SAH plane over the three axes) or ``"cycle"`` (paper: depth % 3).
    empty_bonus : float
        Fraction by which a split that leaves one child empty is favoured.
    clip_triangles : bool
        Classify triangles by exact overlap with each node (perfect splits) instead of
        by their bounding boxes (the paper's naive build).
    """

    traversal_cost: float = 1.0
    intersection_cost: float = 5.0
    min_leaf_size: int = 2
    depth_base: float = 8.0
    depth_log_factor: float = 1.3
    axis_selection: str = "all"
    empty_bonus: float = 0.2
    clip_triangles: bool = False

    def __post_init__(self) -> None:
        if self.traversal_cost < 0 or self.intersection_cost <= 0:
            raise ValueError("kdtree costs must be K_T >= 0 and K_I > 0")
        if self.min_leaf_size < 1:
            raise ValueError("kdtree.min_leaf_size must be >= 1")
        if self.axis_selection not in ("all", "cycle"):
            raise ValueError("kdtree.axis_selection must be 'all' or 'cycle'")
        if not 0.0 <= self.empty_bonus < 1.0:
            raise ValueError("kdtree.empty_bonus must be in [0, 1)")


@dataclass(frozen=True)
class CacheConfig:
    """On-disk cache of content-hashed artefacts (trees, references, models)."""

    directory: str = ".cache/kdtrace"


@dataclass(frozen=True)
class EmbreeCheckConfig:
    """Settings of the Embree agreement check (rays per kind, RNG seed)."""

    rays_per_kind: int = 1_000_000
    seed: int = 20261122


@dataclass(frozen=True)
class ProfileConfig:
    """What one report profile runs.

    Attributes
    ----------
    scenes : tuple of str
        Scene names (``scenes/*.toml``).
    agreement_rays_per_kind : int
        Rays of each kind in the Embree agreement check.
    timing_rays : int
        Incoherent rays timed per tree and Embree.
    frame_width, frame_height, frame_spp : int
        The primary-ray frame timed for Table 1 (pixels, samples per pixel).
    seed : int
        Seed of every ray generator.
    """

    scenes: tuple[str, ...] = ()
    agreement_rays_per_kind: int = 100_000
    timing_rays: int = 200_000
    frame_width: int = 256
    frame_height: int = 256
    frame_spp: int = 4
    seed: int = 20261122

    def __post_init__(self) -> None:
        object.__setattr__(self, "scenes", tuple(self.scenes))
        if min(self.agreement_rays_per_kind, self.timing_rays, self.frame_width, self.frame_height, self.frame_spp) < 1:
            raise ValueError("profile ray counts and frame sizes must be positive")


@dataclass(frozen=True)
class RenderConfig:
    """Defaults of the path tracer (``kdtrace.render``).

    Attributes
    ----------
    spp : int
        Samples (paths) per pixel.
    max_depth : int
        Longest path in segments, Mitsuba 3's ``path`` convention (1: only emitters seen
        directly, 2: direct light, 3: one indirect bounce; -1: unbounded with Russian roulette).
    rr_depth : int
        Depth from which Russian roulette may end a path (Mitsuba's ``rr_depth``).
    seed : int
        Key of the counter-based random number generator.
    tile_size : int
        Side of the square pixel tiles rendered in parallel (does not change the image).
    eye_separation : float
        Distance between the two pinholes of a stereo pair, scene units.
    """

    spp: int = 4
    max_depth: int = 3
    rr_depth: int = 5
    seed: int = 0
    tile_size: int = 16
    eye_separation: float = 0.065

    def __post_init__(self) -> None:
        if self.spp < 1 or self.tile_size < 1 or self.rr_depth < 1:
            raise ValueError("render.spp, render.tile_size and render.rr_depth must be >= 1")
        if self.max_depth < 1 and self.max_depth != -1:
            raise ValueError("render.max_depth must be >= 1 or -1 (unbounded)")
        if not self.eye_separation > 0.0:
            raise ValueError("render.eye_separation must be positive")


@dataclass(frozen=True)
class Config:
    """The whole resolved configuration."""

    kdtree: KDTreeConfig = KDTreeConfig()
    cache: CacheConfig = CacheConfig()
    embree_check: EmbreeCheckConfig = EmbreeCheckConfig()
    render: RenderConfig = RenderConfig()
    profiles: dict[str, ProfileConfig] = dataclasses.field(default_factory=dict)

    def profile(self, name: str) -> ProfileConfig:
        """The named profile; an unknown name lists the known ones."""
        if name not in self.profiles:
            raise ValueError(f"unknown profile {name!r}; known profiles: {', '.join(sorted(self.profiles))}")
        return self.profiles[name]

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict, for recording in result files."""
        return dataclasses.asdict(self)


_SECTIONS = {
    "kdtree": KDTreeConfig,
    "cache": CacheConfig,
    "embree_check": EmbreeCheckConfig,
    "render": RenderConfig,
}


def _merge(base: dict[str, Any], overlay: dict[str, Any], origin: str) -> dict[str, Any]:
    merged = {key: dict(value) for key, value in base.items()}
    for name, values in overlay.get("profiles", {}).items():
        unknown = set(values) - {f.name for f in dataclasses.fields(ProfileConfig)}
        if unknown:
            raise ValueError(f"{origin}: unknown keys in [profiles.{name}]: {sorted(unknown)}")
        merged["profiles"][name] = {**merged["profiles"].get(name, {}), **values}
    for section, values in overlay.items():
        if section == "profiles":
            continue
        if section not in _SECTIONS:
            raise ValueError(f"{origin}: unknown section [{section}]; known: {sorted(_SECTIONS)}")
        known = {f.name for f in dataclasses.fields(_SECTIONS[section])}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"{origin}: unknown keys in [{section}]: {sorted(unknown)}; known: {sorted(known)}")
        merged.setdefault(section, {}).update(values)
    return merged


def load_config(path: str | Path | None = None) -> Config:
    """Load the defaults, overlaid with the TOML file at ``path`` when given.

    Raises
    ------
    ValueError
        On unknown sections or keys, or values out of range.
    """
    with open(DEFAULTS_PATH, "rb") as handle:
        values = tomllib.load(handle)
    if path is not None:
        with open(path, "rb") as handle:
            values = _merge(values, tomllib.load(handle), str(path))
    profiles = {name: ProfileConfig(**entry) for name, entry in values.get("profiles", {}).items()}
    return Config(**{name: cls(**values.get(name, {})) for name, cls in _SECTIONS.items()}, profiles=profiles)


DEFAULT_CONFIG = load_config()
