"""Resolved configuration: frozen dataclasses built from ``defaults.toml``.

Every tunable of kdtrace lives in ``kdtrace/defaults.toml``; this module turns that
file (optionally overlaid with a user TOML file) into immutable dataclasses, so a
result file can record exactly the configuration that produced it.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DEFAULTS_PATH = Path(__file__).with_name("defaults.toml")


#: Ray-triangle tests the traversal offers (:attr:`KDTreeConfig.triangle_test`).
TRIANGLE_TESTS = ("watertight", "moller-trumbore")
#: Learning-rate schedules of the denoisers after their warm-up (ReconstructionProfile.denoiser_decay).
DECAYS = ("constant", "cosine")


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
    split_candidates : str
        Planes the SAH tries: ``"bounds"`` (every triangle bound: the exact sweep) or
        ``"centroids"`` (the paper's FindPlaneSAH: the triangles' centroids).
    clip_triangles : bool
        Classify triangles by exact overlap with each node (perfect splits) instead of
        by their bounding boxes (the paper's naive build).
    triangle_test : str
        Ray-triangle test of the traversal: ``"watertight"`` (Woop, Benthin, Wald 2013;
        no ray slips between triangles sharing an edge) or ``"moller-trumbore"``. Not a
        build parameter: trees are cached and shared across both.
    vector_spans : bool
        Ray queries on watertight trees (the batch queries and the path tracer's) find a node's
        triangles hit all at once before testing those one by one (same results;
        ``kdtrace._kdtree_traverse.span_hits``). Not a build parameter either.
    regroup_min_bytes : int
        Batch ray queries (``KDTree.intersect``, ``KDTree.occluded``) on trees whose traversal data
        and triangle corners take at least this many bytes trace their rays grouped by origin cell
        and direction octant (``kdtrace._ray_order``), results in the caller's order. Not a build
        parameter.
    """

    traversal_cost: float = 1.0
    intersection_cost: float = 5.0
    min_leaf_size: int = 16
    depth_base: float = 8.0
    depth_log_factor: float = 1.3
    axis_selection: str = "all"
    empty_bonus: float = 0.2
    split_candidates: str = "bounds"
    clip_triangles: bool = False
    triangle_test: str = "watertight"
    vector_spans: bool = True
    regroup_min_bytes: int = 2_000_000

    def __post_init__(self) -> None:
        if self.traversal_cost < 0 or self.intersection_cost <= 0:
            raise ValueError("kdtree costs must be K_T >= 0 and K_I > 0")
        if self.min_leaf_size < 1:
            raise ValueError("kdtree.min_leaf_size must be >= 1")
        if self.axis_selection not in ("all", "cycle"):
            raise ValueError("kdtree.axis_selection must be 'all' or 'cycle'")
        if self.split_candidates not in ("bounds", "centroids"):
            raise ValueError("kdtree.split_candidates must be 'bounds' or 'centroids'")
        if not 0.0 <= self.empty_bonus < 1.0:
            raise ValueError("kdtree.empty_bonus must be in [0, 1)")
        if self.triangle_test not in TRIANGLE_TESTS:
            raise ValueError(f"kdtree.triangle_test must be one of {TRIANGLE_TESTS}, got {self.triangle_test!r}")


@dataclass(frozen=True)
class CacheConfig:
    """On-disk cache of content-hashed artefacts (trees, references, models).

    Attributes
    ----------
    directory : str
        The cache folder (``KDTRACE_CACHE`` overrides).
    claim_timeout_seconds : float
        How long a process waits for another one computing the same artefact before computing
        it too (:func:`kdtrace.cache.claim`); longer than the longest training.
    """

    directory: str = ".cache/kdtrace"
    claim_timeout_seconds: float = 14400.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.claim_timeout_seconds) and self.claim_timeout_seconds > 0):
            raise ValueError("cache.claim_timeout_seconds must be a positive number of seconds")


@dataclass(frozen=True)
class EmbreeCheckConfig:
    """Settings of the Embree agreement check (rays per kind, RNG seed)."""

    rays_per_kind: int = 1_000_000
    seed: int = 20261122


@dataclass(frozen=True)
class ProductionConfig:
    """Table 1 at production scale (``kdtrace production``, :mod:`reports.production`).

    Attributes
    ----------
    base_scene : str
        The shipped scan copied to make the scene (:func:`kdtrace.procedural.instanced_scene`).
    triangles : int
        The scene has at least this many triangles.
    terrain_cells : int
        Cells per side of the displaced terrain under the copies (two triangles each).
    seed : int
        Seed of the placements, the terrain and every ray set.
    agreement_rays_per_kind : int
        Rays per kind of the Embree agreement check (its disagreements judged by the float64 oracle).
    oracle_rays : int
        Incoherent rays whose every answer is checked against the float64 oracle (every ray
        against every triangle, so a few thousand at most).
    scaling_sizes : tuple of int
        Triangle counts of the build-scaling measurement (nested subsets of the scene), ascending;
        counts above the scene's triangles are left out.
    """

    base_scene: str = "samurai-monastery"
    triangles: int = 10_000_000
    terrain_cells: int = 256
    seed: int = 20261206
    agreement_rays_per_kind: int = 20_000
    oracle_rays: int = 1_000
    scaling_sizes: tuple[int, ...] = (10_000, 31_623, 100_000, 316_228, 1_000_000, 3_162_278, 10_000_000)

    def __post_init__(self) -> None:
        object.__setattr__(self, "scaling_sizes", tuple(int(size) for size in self.scaling_sizes))
        if self.triangles < 1 or self.terrain_cells < 0 or self.agreement_rays_per_kind < 1 or self.oracle_rays < 1:
            raise ValueError("production.triangles, agreement_rays_per_kind and oracle_rays must be >= 1 and "
                             "terrain_cells >= 0")
        sizes = self.scaling_sizes
        if not sizes or sizes[0] < 1 or list(sizes) != sorted(set(sizes)):
            raise ValueError(f"production.scaling_sizes must be ascending distinct positive counts, got {list(sizes)}")


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
    reconstruction_profile : str
        Name of the ``[reconstruction.profiles.*]`` entry used for datasets and training.
    reconstruction_scenes : tuple of str
        Scenes with a per-scene denoiser (Tables 2, 3, 5, 6); the mixed model trains on all of them.
    unseen_scene : str
        A scene the mixed model never sees in training (the paper's "Pine", Table 3): near
        the training scenes (another object in a training scene's box).
    far_unseen_scene : str
        A second never-seen scene far from the training scenes ("" for none), so Table 3
        shows how the mixed model degrades from near to far.
    build_scaling_scene : str
        Scene whose nested triangle subsets time the KD-tree build against triangle count
        (Table 1's build scaling, :mod:`reports.build_scaling`); "" for none. Measured only
        when the scene is among ``scenes`` (so ``--scenes`` without it skips it).
    sensitivity_scenes : tuple of str
        Scenes whose trees are also built with the paper's recipe (axes cycled by depth,
        centroid candidates), to show under which tree its local-branch claims hold
        (:mod:`reports.sensitivity`); only those among ``scenes`` are measured.
    variant_scenes : tuple of str
        Reconstruction scenes that also get the documented normal + depth variant of the
        per-scene denoiser (auxiliary albedo, normal and depth; Table 2), measured on the same
        test views. Empty for none: each costs one more per-scene training.
    demodulated_scenes : tuple of str
        Reconstruction scenes that also get the albedo-demodulated variant of the per-scene
        denoiser (the paper's network between a division and a multiplication by the albedo,
        :class:`reconstruction.models.Denoiser`; Table 2). Empty for none; one more training each.
    perceptual_scenes : tuple of str
        Reconstruction scenes that also get the perceptual variant of the per-scene denoiser
        (the paper's network trained in a display-like transfer, ``Denoiser(perceptual=G)`` with
        G the reconstruction profile's ``denoiser_perceptual_gain``; Table 2). Empty for none;
        one more training each.
    perceptual_mixed : bool
        Also train the mixed model in that transfer and measure it beside the paper's mixed model
        (Table 3, the unseen scenes included); one more mixed training.
    superres_display : bool
        Also train the superresolution net on display-encoded images
        (``Superresolution(space="display")``) and measure it beside the paper's linear one
        against bicubic upsampling of the same displayed images (Table 5); one more training.
    sweep_spp : tuple of int
        Samples per pixel of the run-time-against-error sweep (our path tracer and Mitsuba).
    sweep_width, sweep_height : int
        Frame size of the sweep, pixels.
    sweep_reference_spp : int
        Mitsuba samples per pixel of the sweep's reference.
    combined_width, combined_height : int
        Final frame size of the §6.4 pipeline (render at half size, denoise, superresolve 2x).
    combined_reference_spp : int
        Mitsuba samples per pixel of the §6.4 pipeline's full-size reference.
    """

    scenes: tuple[str, ...] = ()
    agreement_rays_per_kind: int = 100_000
    timing_rays: int = 200_000
    frame_width: int = 256
    frame_height: int = 256
    frame_spp: int = 4
    seed: int = 20261122
    reconstruction_profile: str = "quick"
    reconstruction_scenes: tuple[str, ...] = ()
    unseen_scene: str = ""
    far_unseen_scene: str = ""
    build_scaling_scene: str = ""
    sensitivity_scenes: tuple[str, ...] = ()
    variant_scenes: tuple[str, ...] = ()
    demodulated_scenes: tuple[str, ...] = ()
    perceptual_scenes: tuple[str, ...] = ()
    perceptual_mixed: bool = False
    superres_display: bool = False
    sweep_spp: tuple[int, ...] = (1, 2, 4, 8, 16, 32)
    sweep_width: int = 128
    sweep_height: int = 128
    sweep_reference_spp: int = 1024
    combined_width: int = 256
    combined_height: int = 256
    combined_reference_spp: int = 256

    def __post_init__(self) -> None:
        for name in ("scenes", "reconstruction_scenes", "variant_scenes", "demodulated_scenes", "perceptual_scenes",
                     "sweep_spp"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        if min(self.agreement_rays_per_kind, self.timing_rays, self.frame_width, self.frame_height, self.frame_spp,
               self.sweep_width, self.sweep_height, self.sweep_reference_spp, self.combined_reference_spp,
               *self.sweep_spp) < 1:
            raise ValueError("profile ray counts, spp and frame sizes must be positive")
        if self.combined_width % 2 or self.combined_height % 2 or min(self.combined_width, self.combined_height) < 2:
            raise ValueError("profile combined_width/height must be positive and even (2x superresolution)")
        if self.far_unseen_scene and self.far_unseen_scene in (*self.reconstruction_scenes, self.unseen_scene):
            raise ValueError(f"profile far_unseen_scene {self.far_unseen_scene!r} must not be a reconstruction "
                             "scene or the unseen_scene")
        for name in ("variant_scenes", "demodulated_scenes", "perceptual_scenes"):
            stray = sorted(set(getattr(self, name)) - set(self.reconstruction_scenes))
            if stray:
                raise ValueError(f"profile {name} {stray} are not among reconstruction_scenes")
        if self.unseen_scene and self.unseen_scene in self.reconstruction_scenes:
            raise ValueError(f"profile unseen_scene {self.unseen_scene!r} must not be one of reconstruction_scenes")


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
    camera_packets : bool
        Trace camera rays in packets of coherent rays (same image as one by one).
    shadow_packets : bool
        Trace the shadow rays of the first hits of a packet's camera rays as one packet of
        occlusion queries (watertight trees; same image as one by one).
    last_ray_max_emitters : int
        Trace a path's last ray against the emitter triangles one by one, and the tree only
        for occlusion, when the scene has at most this many emitter triangles (same image;
        ``kdtrace._render_kernels.last_ray_hit``); 0 turns it off.
    """

    spp: int = 4
    max_depth: int = 3
    rr_depth: int = 5
    seed: int = 0
    tile_size: int = 16
    eye_separation: float = 0.065
    camera_packets: bool = True
    shadow_packets: bool = True
    last_ray_max_emitters: int = 16

    def __post_init__(self) -> None:
        if self.last_ray_max_emitters < 0:
            raise ValueError("render.last_ray_max_emitters must be >= 0")
        if self.spp < 1 or self.tile_size < 1 or self.rr_depth < 1:
            raise ValueError("render.spp, render.tile_size and render.rr_depth must be >= 1")
        if self.max_depth < 1 and self.max_depth != -1:
            raise ValueError("render.max_depth must be >= 1 or -1 (unbounded)")
        if not self.eye_separation > 0.0:
            raise ValueError("render.eye_separation must be positive")


@dataclass(frozen=True)
class ReconstructionProfile:
    """Dataset and training settings of the reconstruction networks (paper §4.2-§5.2, §6.1).

    Attributes
    ----------
    positions : int
        Camera positions drawn uniformly inside the user-movement region (paper: 20).
    views_per_position : int
        View directions per position: yaw turns of the default view direction about the
        camera's up axis, ``yaw_step_degrees`` apart, in the order 0, +1, -1, +2, ... steps
        (paper: 16 views, 22.5 degrees apart, a full turn).
    yaw_step_degrees : float
        Angle between neighbouring view directions, degrees.
    region_fraction : float
        Side of the cubic user-movement region around the default camera, as a fraction of
        the diagonal of the scene's bounding box.
    min_coverage : float
        A view whose camera rays hit geometry in fewer than this fraction of pixels is
        rejected (it sees almost nothing).
    width, height : int
        Resolution of every view, pixels (paper: 512 x 512).
    spp, max_depth : int
        Samples per pixel and path length (Mitsuba convention) of the noisy input.
    reference : str
        ``"mitsuba"`` (Mitsuba 3 ``path``) or ``"kdtrace"`` (our path tracer at ``reference_spp``).
    reference_spp : int
        Samples per pixel of the reference (paper: 1024-4096).
    crop_size, crops_per_view : int
        Side of the square training crops, pixels, and crops drawn per view (paper: 128, 32).
    crops_per_view_by_scene : dict of str -> int
        Scenes whose views give another number of denoiser crops than ``crops_per_view``, in
        every model that learns from them (their per-scene nets and the mixed model); kept as
        sorted (scene, count) pairs. Read it through :meth:`crops_for`.
    test_reference_spp_by_scene : dict of str -> int
        Scenes whose **test views** are scored against references of more samples per pixel
        than ``reference_spp`` (:mod:`reconstruction.test_references`: the extra samples are
        rendered with an independent seed and averaged in), because their reference noise
        would otherwise move the PSNRs measured against them. Training and validation views,
        the datasets' keys and every model's key are unchanged. Kept as sorted (scene, spp)
        pairs; read it through :meth:`test_reference_spp`.
    validation_fraction, test_fraction : float
        Fractions of the accepted views held out for validation and test (split by view).
    epochs, batch_size : int
        Training length and mini-batch size (paper: 100, 32).
    learning_rate : float
        Adam step size.
    superres_crop_size, superres_crops_per_image : int
        Side of the superresolution target crops, pixels (paper: 256), and crops drawn per
        photograph or rendered view.
    superres_downsample : str
        How the low-resolution input is made before bicubic upsampling: ``"area"`` (2x2 box
        mean, what a half-resolution render with a box filter sees) or ``"bicubic"``
        (antialiased bicubic).
    superres_augment : bool
        Augment the training photographs: each gives ``8 x superres_crops_per_image`` crops,
        each under a random one of the 8 flips / 90-degree rotations and a random exposure
        (linear scale in [0.5, 1.5]), so the few bundled photos are not outnumbered by the
        renders. Validation and test data are never augmented.
    precision : str
        Training arithmetic: ``"fp32"``, or ``"bf16"`` (mixed precision: forward and backward
        under ``torch.autocast("cpu", dtype=torch.bfloat16)``, fp32 master weights and Adam
        state, the loss in fp32), or ``"auto"`` (bf16 when the CPU has AVX512-BF16 or AMX,
        else fp32 with a note in the result). Evaluation is always fp32.
    patience : int
        Early stopping: training ends after this many epochs without a lower validation loss
        (0: run all ``epochs``).
    denoiser_epochs : int
        Epochs of each per-scene denoiser, the paper's net and its variants (0: ``epochs``, which
        superresolution keeps).
    mixed_epochs : int
        Epochs of the mixed model, whose epoch holds every scene's crops (0: the per-scene
        denoisers' count).
    denoiser_edge_range_floor : float
        Smallest target LoG range the denoiser loss's edge maps are normalised by
        (:class:`reconstruction.loss.EdgeAwareLoss`; default
        :data:`reconstruction.loss.DENOISER_RANGE_FLOOR`, which says how it was chosen).
    normal_depth_warmup_steps : int
        Linear learning-rate warm-up, in Adam steps, of the normal + depth denoiser variant only
        (:func:`reconstruction.train.fit`; 0: none). Without it that variant's first full-rate
        steps switched off its first encoder layer and it learned the identity (README).
    denoiser_perceptual_gain : float
        G of the perceptual denoiser variant's transfer ``log1p(G·v) / log1p(G)`` of exposed
        radiance v (:class:`reconstruction.models.Denoiser`); > 0.
    denoiser_learning_rate : float or None
        Peak Adam step size of every denoiser (None: ``learning_rate``, which superresolution
        keeps).
    denoiser_decay : str
        The denoisers' learning rate after the warm-up: ``"constant"``, or ``"cosine"`` (half a
        cosine from the peak down to 0 over all the training's Adam steps; the schedule then
        depends on ``epochs``, so it is part of the model's cache key).
    denoiser_warmup_steps : int
        Linear learning-rate warm-up, in Adam steps, of every denoiser (0: none); a variant with
        a longer warm-up of its own (``normal_depth_warmup_steps``) keeps the longer one.
    model_store : str
        Folder, relative to the repository, where each finished model is copied
        (``<model_store>/<kind>-<key>``: kept weights, history, plot, ``result.json``) and found
        again by a machine whose cache lacks it (:mod:`reconstruction.train`); "" for none.
        Not part of any cache key.
    seed : int
        Seed of camera positions, render seeds, crops, splits, initialisation and shuffling.
    """

    positions: int = 20
    views_per_position: int = 16
    yaw_step_degrees: float = 22.5
    region_fraction: float = 0.1
    min_coverage: float = 0.25
    width: int = 512
    height: int = 512
    spp: int = 4
    max_depth: int = 3
    reference: str = "mitsuba"
    reference_spp: int = 1024
    crop_size: int = 128
    crops_per_view: int = 32
    crops_per_view_by_scene: tuple[tuple[str, int], ...] = ()
    test_reference_spp_by_scene: tuple[tuple[str, int], ...] = ()
    validation_fraction: float = 0.15
    test_fraction: float = 0.15
    epochs: int = 100
    batch_size: int = 32
    learning_rate: float = 1e-3
    superres_crop_size: int = 256
    superres_crops_per_image: int = 32
    superres_downsample: str = "area"
    superres_augment: bool = False
    precision: str = "fp32"
    patience: int = 0
    denoiser_epochs: int = 0
    mixed_epochs: int = 0
    denoiser_edge_range_floor: float = 0.1
    normal_depth_warmup_steps: int = 0
    denoiser_perceptual_gain: float = 8.0
    denoiser_learning_rate: float | None = None
    denoiser_decay: str = "constant"
    denoiser_warmup_steps: int = 0
    model_store: str = ""
    seed: int = 20261122

    @property
    def denoiser_rate(self) -> float:
        """Peak learning rate of the denoisers: ``denoiser_learning_rate``, else ``learning_rate``."""
        return self.learning_rate if self.denoiser_learning_rate is None else self.denoiser_learning_rate

    def crops_for(self, scene_name: str) -> int:
        """Denoiser crops drawn per view of ``scene_name``."""
        return dict(self.crops_per_view_by_scene).get(scene_name, self.crops_per_view)

    def test_reference_spp(self, scene_name: str) -> int:
        """Samples per pixel of the references ``scene_name``'s test views are scored against."""
        return dict(self.test_reference_spp_by_scene).get(scene_name, self.reference_spp)

    @property
    def denoiser(self) -> ReconstructionProfile:
        """This profile with a per-scene denoiser's epoch count as ``epochs``."""
        return dataclasses.replace(self, epochs=self.denoiser_epochs or self.epochs, denoiser_epochs=0)

    @property
    def mixed(self) -> ReconstructionProfile:
        """This profile with the mixed model's epoch count as ``epochs``."""
        return dataclasses.replace(self, epochs=self.mixed_epochs or self.denoiser_epochs or self.epochs, denoiser_epochs=0,
                                   mixed_epochs=0)

    def _scene_counts(self, field: str, what: str) -> dict[str, int]:
        """Check a scene -> count field (a TOML table or the pairs) and store it as sorted pairs."""
        by_scene = dict(getattr(self, field))
        if not all(isinstance(name, str) and isinstance(count, int) for name, count in by_scene.items()):
            raise ValueError(f"reconstruction.{field} maps scene names to {what}")
        object.__setattr__(self, field, tuple(sorted(by_scene.items())))
        return by_scene

    def __post_init__(self) -> None:
        by_scene = self._scene_counts("crops_per_view_by_scene", "crop counts")
        test_spp = self._scene_counts("test_reference_spp_by_scene", "samples per pixel")
        if any(spp < self.reference_spp for spp in test_spp.values()):
            raise ValueError(f"reconstruction.test_reference_spp_by_scene must be >= reference_spp "
                             f"({self.reference_spp}): a test reference is the dataset's plus more samples")
        counts = (self.positions, self.views_per_position, self.width, self.height, self.spp, self.reference_spp,
                  self.crop_size, self.crops_per_view, *by_scene.values(), self.epochs, self.batch_size, self.superres_crop_size,
                  self.superres_crops_per_image)
        if min(counts) < 1:
            raise ValueError("reconstruction counts, sizes, spp, epochs and batch size must be >= 1")
        if self.max_depth < 1 and self.max_depth != -1:
            raise ValueError("reconstruction.max_depth must be >= 1 or -1 (unbounded)")
        if self.reference not in ("mitsuba", "kdtrace"):
            raise ValueError("reconstruction.reference must be 'mitsuba' or 'kdtrace'")
        if self.superres_downsample not in ("area", "bicubic"):
            raise ValueError("reconstruction.superres_downsample must be 'area' or 'bicubic'")
        if self.precision not in ("fp32", "bf16", "auto"):
            raise ValueError("reconstruction.precision must be 'fp32', 'bf16' or 'auto'")
        if self.mixed_epochs < 0 or self.denoiser_epochs < 0:
            raise ValueError("reconstruction.denoiser_epochs and mixed_epochs must be >= 0 (0: the default count)")
        if self.patience < 0:
            raise ValueError("reconstruction.patience must be >= 0 (0: no early stopping)")
        if self.normal_depth_warmup_steps < 0 or self.denoiser_warmup_steps < 0:
            raise ValueError("reconstruction.normal_depth_warmup_steps and denoiser_warmup_steps must be >= 0 "
                             "(0: no warm-up)")
        if self.denoiser_decay not in DECAYS:
            raise ValueError(f"reconstruction.denoiser_decay must be one of {DECAYS}, got {self.denoiser_decay!r}")
        if self.denoiser_learning_rate is not None and not self.denoiser_learning_rate > 0.0:
            raise ValueError("reconstruction.denoiser_learning_rate must be > 0 (or absent: learning_rate)")
        if not (math.isfinite(self.denoiser_perceptual_gain) and self.denoiser_perceptual_gain > 0):
            raise ValueError("reconstruction.denoiser_perceptual_gain must be a positive finite number")
        if not self.denoiser_edge_range_floor > 0:
            raise ValueError("reconstruction.denoiser_edge_range_floor must be > 0")
        if self.superres_crop_size % 2:
            raise ValueError("reconstruction.superres_crop_size must be even (2x downsampling)")
        if not (0.0 <= self.region_fraction and 0.0 <= self.min_coverage <= 1.0 and self.learning_rate > 0.0):
            raise ValueError("reconstruction.region_fraction >= 0, min_coverage in [0, 1], learning_rate > 0")
        if not (0.0 < self.validation_fraction and 0.0 < self.test_fraction
                and self.validation_fraction + self.test_fraction < 1.0):
            raise ValueError("reconstruction validation and test fractions must be > 0 and sum below 1")


@dataclass(frozen=True)
class ReconstructionConfig:
    """Named :class:`ReconstructionProfile` s (``[reconstruction.profiles.NAME]``)."""

    profiles: dict[str, ReconstructionProfile] = dataclasses.field(default_factory=dict)

    def __post_init__(self) -> None:
        object.__setattr__(self, "profiles", {
            name: entry if isinstance(entry, ReconstructionProfile) else ReconstructionProfile(**entry)
            for name, entry in self.profiles.items()})

    def profile(self, name: str) -> ReconstructionProfile:
        """The named profile; an unknown name lists the known ones."""
        if name not in self.profiles:
            raise ValueError(f"unknown reconstruction profile {name!r}; known: {', '.join(sorted(self.profiles))}")
        return self.profiles[name]


@dataclass(frozen=True)
class GateConfig:
    """Tolerances of the CI regression gate (:mod:`reports.gate`).

    Attributes
    ----------
    ratio_tolerance : float
        Largest allowed relative drop of a same-run speed ratio against the baseline
        (0.35: fails below 65 % of the baseline value).
    ratio_tolerances : dict of str -> float
        Per-metric overrides of ``ratio_tolerance``: ``fnmatch`` pattern of the metric
        name -> relative tolerance; the first matching pattern (in file order) wins.
    psnr_tolerance_db : float
        Largest allowed PSNR drop, dB.
    flip_tolerance : float
        Largest allowed rise of a mean FLIP error (absolute, FLIP is in [0, 1]).
    """

    ratio_tolerance: float = 0.35
    ratio_tolerances: dict[str, float] = dataclasses.field(default_factory=dict)
    psnr_tolerance_db: float = 0.1
    flip_tolerance: float = 0.002

    def __post_init__(self) -> None:
        object.__setattr__(self, "ratio_tolerances", dict(self.ratio_tolerances))
        for tolerance in (self.ratio_tolerance, *self.ratio_tolerances.values()):
            if not 0.0 <= tolerance < 1.0:
                raise ValueError(f"gate ratio tolerances must be in [0, 1), got {tolerance!r}")
        if self.psnr_tolerance_db < 0.0:
            raise ValueError("gate.psnr_tolerance_db must be >= 0")
        if not 0.0 <= self.flip_tolerance < 1.0:
            raise ValueError(f"gate.flip_tolerance must be in [0, 1), got {self.flip_tolerance!r}")

    def tolerance_for(self, name: str) -> float:
        """Relative ratio tolerance of the metric ``name`` (first matching override, else the default)."""
        import fnmatch

        for pattern, tolerance in self.ratio_tolerances.items():
            if fnmatch.fnmatchcase(name, pattern):
                return tolerance
        return self.ratio_tolerance


@dataclass(frozen=True)
class DistributedConfig:
    """Units of work on a Dask cluster (:mod:`kdtrace.distributed`).

    Attributes
    ----------
    scheduler : str
        Address of an existing Dask scheduler (``tcp://host:8786``); empty: start an
        embedded ``LocalCluster``. The environment variable ``KDTRACE_SCHEDULER`` overrides it.
    workers : int
        Worker processes of the embedded cluster; 0: ``cores // threads_per_worker``.
    threads_per_worker : int
        Compute threads of each worker (numba, PyTorch and Dr.Jit), so that workers x
        threads = cores. Each worker runs one unit at a time.
    connect_timeout : float
        Seconds to wait for a scheduler before giving up with an error.
    retries : int
        Extra attempts of a unit that raised an exception (a unit whose worker died is
        rescheduled by Dask regardless, up to ``distributed.scheduler.allowed-failures``).
    dashboard_address : str
        Where the embedded cluster serves its dashboard (``":0"``: any free port; empty: none).
    mitsuba_variant : str
        Mitsuba variant of the references (``"llvm_ad_rgb"``, ``"scalar_rgb"``, ``"cuda_ad_rgb"``);
        empty: the usual choice (``llvm_ad_rgb`` when usable). Unusable variants fall back.
    stale_temporary_seconds : float
        A temporary file of an atomic write older than this (seconds) was left by a
        process that died and is removed when a dataset is completed.
    scaleout_views : int
        Views generated per measurement of the 1- and 2-worker throughput (``reports/scaleout.py``).
    calibration_size : int
        Side of the square frames (pixels) timed to fit the per-view cost model of the projection.
    calibration_spp : tuple of int
        Two reference sample counts timed to fit that model (overhead + cost per sample).
    projection_cores : tuple of int
        Core counts for which the wall time of the ``paper`` datasets is projected.
    """

    scheduler: str = ""
    workers: int = 0
    threads_per_worker: int = 1
    connect_timeout: float = 5.0
    retries: int = 1
    dashboard_address: str = ":0"
    mitsuba_variant: str = ""
    stale_temporary_seconds: float = 600.0
    scaleout_views: int = 12
    calibration_size: int = 96
    calibration_spp: tuple[int, ...] = (16, 64)
    projection_cores: tuple[int, ...] = (2, 64, 256)

    def __post_init__(self) -> None:
        object.__setattr__(self, "calibration_spp", tuple(self.calibration_spp))
        object.__setattr__(self, "projection_cores", tuple(self.projection_cores))
        if self.workers < 0 or self.threads_per_worker < 1 or self.retries < 0:
            raise ValueError("distributed.workers >= 0, threads_per_worker >= 1 and retries >= 0")
        if not (self.connect_timeout > 0 and self.stale_temporary_seconds > 0):
            raise ValueError("distributed.connect_timeout and stale_temporary_seconds must be positive")
        if self.scaleout_views < 3 or self.calibration_size < 8 or min(self.projection_cores, default=0) < 1:
            raise ValueError("distributed.scaleout_views >= 3, calibration_size >= 8, projection_cores >= 1")
        if len(self.calibration_spp) != 2 or not 0 < self.calibration_spp[0] < self.calibration_spp[1]:
            raise ValueError("distributed.calibration_spp must be two increasing positive sample counts")


@dataclass(frozen=True)
class Config:
    """The whole resolved configuration."""

    kdtree: KDTreeConfig = KDTreeConfig()
    cache: CacheConfig = CacheConfig()
    embree_check: EmbreeCheckConfig = EmbreeCheckConfig()
    gate: GateConfig = GateConfig()
    render: RenderConfig = RenderConfig()
    reconstruction: ReconstructionConfig = ReconstructionConfig()
    distributed: DistributedConfig = DistributedConfig()
    production: ProductionConfig = ProductionConfig()
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
    "gate": GateConfig,
    "render": RenderConfig,
    "reconstruction": ReconstructionConfig,
    "distributed": DistributedConfig,
    "production": ProductionConfig,
}


def _merge(base: dict[str, Any], overlay: dict[str, Any], origin: str) -> dict[str, Any]:
    merged = {key: dict(value) for key, value in base.items()}
    for name, values in overlay.get("profiles", {}).items():
        unknown = set(values) - {f.name for f in dataclasses.fields(ProfileConfig)}
        if unknown:
            raise ValueError(f"{origin}: unknown keys in [profiles.{name}]: {sorted(unknown)}")
        merged["profiles"][name] = {**merged["profiles"].get(name, {}), **values}
    if set(overlay.get("reconstruction", {})) - {"profiles"}:
        raise ValueError(f"{origin}: [reconstruction] holds only profiles ([reconstruction.profiles.NAME])")
    for name, values in overlay.get("reconstruction", {}).get("profiles", {}).items():
        unknown = set(values) - {f.name for f in dataclasses.fields(ReconstructionProfile)}
        if unknown:
            raise ValueError(f"{origin}: unknown keys in [reconstruction.profiles.{name}]: {sorted(unknown)}")
        profiles = merged.setdefault("reconstruction", {}).setdefault("profiles", {})
        profiles[name] = {**profiles.get(name, {}), **values}
    for section, values in overlay.items():
        if section in ("profiles", "reconstruction"):
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
