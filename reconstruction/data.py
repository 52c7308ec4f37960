"""Training data of the reconstruction networks (paper §4.2-§4.3 and §5.2).

**Precision Graphics datasets** (the denoiser). Per scene, ``positions`` camera positions
are drawn uniformly inside the *user-movement region*, a cube centred on the scene's
default camera whose side is ``region_fraction`` times the diagonal of the scene's
bounding box. From each position, ``views_per_position`` views turn the default view
direction about the camera's up axis by 0, +1, -1, +2, ... steps of ``yaw_step_degrees``
(the paper: 20 positions x 16 views, 22.5 degrees apart, 512 x 512). Each view holds a
noisy render of our path tracer (``spp``, ``max_depth``) with its albedo (the paper's
diffuse map), shading normal and depth, and a reference (Mitsuba 3 by default, or our
path tracer at ``reference_spp``). A view whose camera rays hit geometry in fewer than
``min_coverage`` of the pixels sees almost nothing and is rejected before its reference
is rendered. Accepted views are split into train / validation / test **by view** (the
paper splits random crops; crops of one view in two splits would leak), and random
square crops are drawn from the views of each split.

Storage: ``cache_root()/datasets/<scene>-<key>/`` with one ``view-NNNN.npz`` per view
(written atomically, so an interrupted run leaves no partial file and a rerun renders
only the missing views) and ``manifest.json`` (scene hash, settings, seeds, views with
the worker and seconds of each, splits, provenance), written last. The folder key
hashes the scene's content, the profile's dataset settings and :data:`RECIPE_VERSION`,
so a changed scene or setting gets a new folder and an unchanged one is reused.

**Units of work.** One view (noisy render with its auxiliary buffers, then the reference
if the view is accepted) is one idempotent unit, :func:`make_view`; it runs in this
process or, with ``scheduler``/``workers``/``client`` or ``$KDTRACE_SCHEDULER``, on Dask
workers (:mod:`kdtrace.distributed`), which then need the dataset folder at the same
path (shared storage on a cluster). Both give the same arrays bit for bit: the seeds
depend only on the view, numba's image does not depend on its thread count, and the
Mitsuba references are rendered on one Dr.Jit thread (its LLVM backend accumulates
samples with atomics, so more threads change the last bits from run to run). An
unwritable folder is a :class:`DatasetWriteError` before anything is rendered.

**Superresolution data** (§5.2). Natural photographs bundled with scikit-image (no
download) plus reference renders; each RGB crop (the target) is reduced 2x (``"area"``:
2x2 box mean, the half-resolution render the network will see; or ``"bicubic"``,
antialiased) and bicubically upsampled back (:func:`reconstruction.models.bicubic_upsample`,
clamped to [0, 1] like the inference path) to give the input. Targets are clipped to
[0, 1] (the superresolution network works on display-range luma). Photos are
sRGB-decoded to linear RGB like the renders. Training uses the photos and the renders
of the training views; validation a held-out photo and the validation views; test only
renders (test views).
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import math
import os
import re
import shutil
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from kdtrace.cache import (
    DiskFullError,
    atomic_write_bytes,
    cache_root,
    compute_once,
    content_key,
    load_npz,
    save_npz,
)
from kdtrace.config import DEFAULT_CONFIG, DistributedConfig, ReconstructionProfile
from kdtrace.imageio import srgb_decode
from kdtrace.provenance import stamp
from kdtrace.resources import require_memory
from kdtrace.scene import Camera, Scene

#: Bump when the way views are made changes: old datasets become cache misses.
RECIPE_VERSION = 1
#: Profile fields a dataset depends on (the training fields do not change it).
DATASET_FIELDS = ("positions", "views_per_position", "yaw_step_degrees", "region_fraction", "min_coverage",
                  "width", "height", "spp", "max_depth", "reference", "reference_spp",
                  "validation_fraction", "test_fraction", "seed")
#: Buffers stored per accepted view: name -> channels.
BUFFERS = {"noisy": 3, "albedo": 3, "normal": 3, "depth": 1, "reference": 3}
SPLITS = ("train", "validation", "test")
#: Photographs shipped inside scikit-image (``skimage/data/*``), no download needed.
TRAIN_PHOTOS = ("astronaut", "coffee", "rocket", "retina", "immunohistochemistry")
VALIDATION_PHOTOS = ("chelsea",)


@dataclass(frozen=True)
class ViewSpec:
    """One candidate view of a dataset.

    Attributes
    ----------
    index : int
        Position in the candidate list (``position * views_per_position + yaw``).
    position, yaw : int
        Index of the camera position and of the yaw step.
    yaw_degrees : float
        Turn of the default view direction about the up axis, degrees.
    camera : Camera
        The pinhole, at the dataset's resolution.
    noisy_seed, reference_seed : int
        Seeds of the noisy render and of the reference, in [0, 2**32).
    """

    index: int
    position: int
    yaw: int
    yaw_degrees: float
    camera: Camera
    noisy_seed: int
    reference_seed: int

    @property
    def name(self) -> str:
        """File stem of the view, ``view-NNNN``."""
        return f"view-{self.index:04d}"


@dataclass(frozen=True)
class Dataset:
    """A generated Precision Graphics dataset (see the module docstring).

    Attributes
    ----------
    root : Path
        Its folder.
    manifest : dict
        Contents of ``manifest.json``: ``key``, ``scene``, ``scene_hash``, ``settings``,
        ``views`` (per candidate: name, camera, seeds, coverage, accepted), ``splits``
        (split -> accepted view names) and ``provenance``.
    """

    root: Path
    manifest: dict[str, Any]

    @property
    def key(self) -> str:
        """Content key of the dataset (also in its folder name)."""
        return self.manifest["key"]

    def views(self, split: str | None = None) -> list[str]:
        """Names of the accepted views, all or those of one split."""
        if split is None:
            return [name for part in SPLITS for name in self.manifest["splits"][part]]
        if split not in SPLITS:
            raise ValueError(f"unknown split {split!r}; known: {', '.join(SPLITS)}")
        return list(self.manifest["splits"][split])

    def load_view(self, name: str) -> dict[str, np.ndarray]:
        """The buffers of one accepted view: name -> float32 (H, W, C) array (see :data:`BUFFERS`).

        Raises
        ------
        ValueError
            The view file is missing, unreadable or from another dataset.
        """
        loaded = load_npz(self.root / f"{name}.npz")
        if loaded is None or loaded[1].get("key") != self.key or not loaded[1].get("accepted"):
            raise ValueError(f"{self.root / name}.npz is missing, corrupt or not an accepted view of this dataset")
        return loaded[0]


# ------------------------------------------------------------------ views
def _turn(vector: np.ndarray, axis: np.ndarray, degrees: float) -> np.ndarray:
    """Rodrigues rotation of ``vector`` about the unit ``axis``."""
    angle = math.radians(degrees)
    return (vector * math.cos(angle) + np.cross(axis, vector) * math.sin(angle)
            + axis * np.dot(axis, vector) * (1.0 - math.cos(angle)))


def yaw_steps(count: int) -> list[int]:
    """Yaw steps 0, +1, -1, +2, -2, ... (``count`` of them), nearest the default view first."""
    return [(k + 1) // 2 * (1 if k % 2 else -1) for k in range(count)]


def movement_region(scene: Scene, fraction: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corner of the user-movement cube around the default camera.

    Parameters
    ----------
    scene : Scene
    fraction : float
        Side of the cube as a fraction of the bounding-box diagonal of the scene.

    Returns
    -------
    lower, upper : (3,) float64 ndarray
        Corners, scene units.
    """
    lower, upper = scene.bounds
    half = 0.5 * fraction * float(np.linalg.norm(upper - lower))
    centre = np.asarray(scene.camera.position, np.float64)
    return centre - half, centre + half


def candidate_views(scene: Scene, profile: ReconstructionProfile) -> list[ViewSpec]:
    """All ``positions x views_per_position`` candidate views of ``scene`` (deterministic in the seed)."""
    base = scene.camera
    rng = np.random.default_rng([profile.seed, 1])
    lower, upper = movement_region(scene, profile.region_fraction)
    positions = rng.uniform(lower, upper, size=(profile.positions, 3))
    forward = np.subtract(base.look_at, base.position).astype(np.float64)
    axis = np.asarray(base.up, np.float64) / np.linalg.norm(base.up)
    views = []
    for p, position in enumerate(positions):
        for y, step in enumerate(yaw_steps(profile.views_per_position)):
            degrees = step * profile.yaw_step_degrees
            camera = Camera(position=tuple(map(float, position)),
                            look_at=tuple(map(float, position + _turn(forward, axis, degrees))),
                            up=base.up, fov=base.fov, width=profile.width, height=profile.height)
            index = p * profile.views_per_position + y
            noisy_seed, reference_seed = np.random.SeedSequence([profile.seed, 2, index]).generate_state(2)
            views.append(ViewSpec(index, p, y, float(degrees), camera, int(noisy_seed), int(reference_seed)))
    return views


def view_camera(record: dict[str, Any]) -> Camera:
    """The :class:`Camera` of a view record of a manifest (its JSON lists back to tuples)."""
    return Camera(**{k: tuple(v) if isinstance(v, list) else v for k, v in record["camera"].items()})


def dataset_key(scene: Scene, profile: ReconstructionProfile) -> str:
    """Content key of the dataset of ``scene`` under ``profile`` (scene, dataset settings, recipe)."""
    settings = {name: getattr(profile, name) for name in DATASET_FIELDS}
    return content_key("precision-graphics-dataset", RECIPE_VERSION, scene.content_hash(), settings)


def dataset_dir(scene: Scene, profile: ReconstructionProfile) -> Path:
    """Folder of the dataset of ``scene`` under ``profile``."""
    stem = re.sub(r"[^A-Za-z0-9_.-]", "_", scene.name)
    return cache_root() / "datasets" / f"{stem}-{dataset_key(scene, profile)[:24]}"


def resolve_profile(profile: str | ReconstructionProfile) -> ReconstructionProfile:
    """The reconstruction profile ``profile`` names in the default configuration, or ``profile`` itself.

    Parameters
    ----------
    profile : str or ReconstructionProfile
        A profile name of ``kdtrace/defaults.toml`` (``quick``, ``standard``, ``paper``), or a profile.

    Returns
    -------
    ReconstructionProfile
    """
    return DEFAULT_CONFIG.reconstruction.profile(profile) if isinstance(profile, str) else profile


def reference_variant(requested: str | None) -> str | None:
    """The Mitsuba variant to ask :func:`references.mitsuba.render_reference` for.

    Parameters
    ----------
    requested : str or None
        ``None``/``""``: the usual choice (``llvm_ad_rgb`` when usable, else ``scalar_rgb``);
        a supported variant: itself; another variant (e.g. ``cuda_ad_rgb`` on a GPU worker):
        itself when :mod:`references.llvm` supports it and it renders here, else the usual
        choice with a warning.

    Returns
    -------
    str or None
    """
    from references.llvm import SUPPORTED_VARIANTS, probe_variant

    if not requested or requested in SUPPORTED_VARIANTS:
        return requested or None
    works, reason = probe_variant(requested, None)
    if not works:
        warnings.warn(f"Mitsuba {requested} unusable on this worker ({reason}); using the default variant",
                      stacklevel=2)
        return None
    warnings.warn(f"Mitsuba {requested} renders here but references.mitsuba supports only {SUPPORTED_VARIANTS}; "
                  "using the default variant", stacklevel=2)
    return None


@contextlib.contextmanager
def _one_jit_thread():
    """Run Dr.Jit's CPU backend on one thread, then restore its thread count.

    With more threads, Mitsuba's LLVM variant adds samples into the film with atomics in
    a varying order, so two renders with the same seed differ in the last bits; on one
    thread a reference is reproducible, and a dataset is the same in-process and on any
    number of workers. The parallelism of a dataset comes from rendering views at once.
    """
    import drjit

    previous = drjit.thread_count()
    drjit.set_thread_count(1)
    try:
        yield
    finally:
        drjit.set_thread_count(previous)


def _render_view(scene: Scene, view: ViewSpec, profile: ReconstructionProfile,
                 variant: str | None = None) -> tuple[dict, dict]:
    """Render one view: (arrays, metadata); arrays are empty when the view is rejected."""
    from kdtrace.render import render

    with warnings.catch_warnings():  # a view that sees nothing is rejected below
        warnings.filterwarnings("ignore", message=".*camera looks at nothing")
        noisy = render(scene, spp=profile.spp, max_depth=profile.max_depth, seed=view.noisy_seed,
                       width=profile.width, height=profile.height, aux=True, camera=view.camera)
    coverage = float(np.mean(noisy.depth > 0.0))
    metadata = {"coverage": coverage, "accepted": coverage >= profile.min_coverage,
                "noisy_seconds": noisy.seconds}
    if not metadata["accepted"]:
        return {}, metadata
    if profile.reference == "mitsuba":
        from references.llvm import activate_variant
        from references.mitsuba import render_reference

        variant = activate_variant(reference_variant(variant))  # before drjit is imported
        with _one_jit_thread():
            reference = render_reference(dataclasses.replace(scene, cameras=[view.camera]),
                                         spp=profile.reference_spp, max_depth=profile.max_depth,
                                         seed=view.reference_seed, width=profile.width, height=profile.height,
                                         cache=False, variant=variant)
        metadata["reference_variant"] = reference.variant
    else:
        reference = render(scene, spp=profile.reference_spp, max_depth=profile.max_depth,
                           seed=view.reference_seed, width=profile.width, height=profile.height, aux=False,
                           camera=view.camera)
    metadata["reference_seconds"] = reference.seconds
    arrays = {"noisy": noisy.rgb, "albedo": noisy.albedo, "normal": noisy.normal,
              "depth": noisy.depth[..., None], "reference": reference.rgb}
    return {name: np.ascontiguousarray(value, np.float32) for name, value in arrays.items()}, metadata


def _view_metadata(path: Path) -> dict[str, Any] | None:
    """The metadata record of a view file, without reading its arrays; None when missing or unreadable."""
    try:
        with np.load(path) as stored:
            return json.loads(stored["__metadata__"].tobytes().decode())
    except (OSError, ValueError, KeyError, EOFError):
        return None


def make_view(scene: Scene, profile: ReconstructionProfile, index: int, root: str | Path, key: str,
              variant: str | None = None) -> dict[str, Any]:
    """Render one candidate view into ``root/view-NNNN.npz``, unless it is already there: a unit of work.

    Idempotent: a file holding this dataset's ``key`` is kept and its record returned.
    The file is written atomically, so concurrent or repeated calls (a retried unit, a
    second client) leave one complete file; the arrays depend only on the seeds.

    Parameters
    ----------
    scene : Scene
    profile : ReconstructionProfile
    index : int
        Candidate index (see :func:`candidate_views`).
    root : str or Path
        Dataset folder (shared storage when the call runs on another machine).
    key : str
        :func:`dataset_key` of ``scene`` and ``profile``.
    variant : str, optional
        Mitsuba variant of the reference (see :func:`reference_variant`).

    Returns
    -------
    dict
        The view's record: name, camera, seeds, coverage, accepted, render seconds, and
        ``worker`` / ``unit_seconds`` (who made the file and its wall time, seconds).
    """
    path = Path(root) / f"view-{index:04d}.npz"

    def stored() -> dict[str, Any] | None:
        metadata = _view_metadata(path)
        return metadata if metadata is not None and metadata.get("key") == key else None

    # claimed: two processes generating one dataset share its views instead of rendering each twice
    return compute_once(path, stored, lambda: _render_and_save_view(scene, profile, index, path, key, variant))


def _render_and_save_view(scene: Scene, profile: ReconstructionProfile, index: int, path: Path, key: str,
                          variant: str | None) -> dict[str, Any]:
    """Render candidate view ``index`` and write it atomically to ``path``; its record (see :func:`make_view`)."""
    from kdtrace.distributed import worker_identity

    view = candidate_views(scene, profile)[index]
    started = time.perf_counter()
    arrays, metadata = _render_view(scene, view, profile, variant)
    metadata = {"key": key, "name": view.name, "index": view.index, "position": view.position,
                "yaw": view.yaw, "yaw_degrees": view.yaw_degrees, "camera": dataclasses.asdict(view.camera),
                "noisy_seed": view.noisy_seed, "reference_seed": view.reference_seed, **metadata,
                "worker": worker_identity(), "unit_seconds": time.perf_counter() - started}
    metadata = json.loads(json.dumps(metadata))
    try:
        save_npz(path, arrays, metadata)
    except DiskFullError as error:  # its message names the bytes needed and free
        raise DatasetWriteError(error.errno, str(error)) from error
    except OSError as error:
        raise DatasetWriteError(error.errno, f"cannot write {path}: {error.strerror or error}; nothing half-written "
                                "was left") from error
    return metadata


class DatasetWriteError(OSError):
    """The dataset folder cannot be written (read-only, full, not a folder)."""


def check_writable(root: Path) -> None:
    """Create ``root`` if needed and write and delete a probe file in it.

    Raises
    ------
    DatasetWriteError
        With the folder and the operating system's reason; nothing in ``root`` changed.
    """
    try:
        root.mkdir(parents=True, exist_ok=True)
        handle, probe = tempfile.mkstemp(dir=root, prefix=".write-probe.")
        try:
            os.write(handle, b"kdtrace")
        finally:
            os.close(handle)
            Path(probe).unlink(missing_ok=True)
    except OSError as error:
        raise DatasetWriteError(error.errno, f"dataset folder {root} is not writable: {error.strerror or error}; "
                                "the dataset was left as it was") from error


def view_bytes(profile: ReconstructionProfile) -> int:
    """Upper bound of the bytes of one stored view: every buffer of :data:`BUFFERS` as uncompressed float32."""
    return profile.width * profile.height * sum(BUFFERS.values()) * 4


def view_memory_bytes(profile: ReconstructionProfile) -> int:
    """Upper bound of the memory of rendering one view in this process: 4 x :func:`view_bytes`.

    The noisy render's buffers (one :func:`view_bytes`), the reference's float64 running sums
    with its float32 mean and variance (72 bytes per pixel, under 1.5 more), and one more for the
    film of Mitsuba and the arrays being written. Views are rendered one at a time, so this does
    not grow with their number.
    """
    return 4 * view_bytes(profile)


def check_disk_space(root: Path, views_to_render: int, profile: ReconstructionProfile) -> None:
    """Refuse, before anything is rendered, a dataset whose views would not fit on ``root``'s disk.

    Raises
    ------
    DatasetWriteError
        ``ENOSPC``, naming the space needed (with a 10% margin) and the space free.
    """
    needed = int(1.1 * views_to_render * view_bytes(profile))
    free = shutil.disk_usage(root).free
    if needed > free:
        raise DatasetWriteError(errno.ENOSPC, f"the dataset in {root} needs up to {needed / 1e9:.2f} GB for "
                                f"{views_to_render} more views of {profile.width}x{profile.height}, but only "
                                f"{free / 1e9:.2f} GB are free; nothing was rendered")


def remove_stale_temporaries(root: Path, older_than: float) -> list[str]:
    """Delete temporary files of atomic writes (``.view-*``, ``.manifest.*``) older than ``older_than`` seconds.

    Such a file is left only by a process that died while writing; a live writer's
    temporary exists for the duration of one ``np.savez``.

    Returns
    -------
    list of str
        Names removed.
    """
    removed = []
    now = time.time()
    for path in list(root.glob(".view-*")) + list(root.glob(".manifest.*")):
        with contextlib.suppress(FileNotFoundError):
            if now - path.stat().st_mtime > older_than:
                path.unlink()
                removed.append(path.name)
    return removed


def split_views(names: list[str], profile: ReconstructionProfile) -> dict[str, list[str]]:
    """Split accepted view names into train / validation / test (seeded shuffle, by view).

    Each held-out split gets ``round(fraction * n)`` views but at least one.

    Raises
    ------
    ValueError
        Fewer than three accepted views (each split needs one).
    """
    if len(names) < 3:
        raise ValueError(f"only {len(names)} accepted views; a train/validation/test split needs at least 3 "
                         "(add positions or views, or lower min_coverage)")
    order = [names[i] for i in np.random.default_rng([profile.seed, 3]).permutation(len(names))]
    n_val = max(1, round(profile.validation_fraction * len(names)))
    n_test = max(1, round(profile.test_fraction * len(names)))
    if n_val + n_test >= len(names):
        n_val = n_test = 1
    return {"validation": sorted(order[:n_val]), "test": sorted(order[n_val:n_val + n_test]),
            "train": sorted(order[n_val + n_test:])}


def generate_dataset(scene: str | Scene, profile: str | ReconstructionProfile = "quick",
                     progress: bool | None = None, *, scheduler: str | None = None, workers: int | None = None,
                     variant: str | None = None, client: Any = None,
                     config: DistributedConfig | None = None) -> Dataset:
    """Generate (or reuse) the Precision Graphics dataset of one scene.

    Parameters
    ----------
    scene : str or Scene
        Scene name (``scenes/*.toml``) or a loaded scene; its first camera defines the
        movement region and the default view direction.
    profile : str or ReconstructionProfile
        A profile of ``[reconstruction.profiles]`` or a profile object.
    progress : bool, optional
        Show a tqdm bar (None: only on a terminal).
    scheduler : str, optional
        Render the views on Dask (:mod:`kdtrace.distributed`): a scheduler address, or
        ``"local"`` for an embedded LocalCluster. Default: ``$KDTRACE_SCHEDULER`` when set,
        else in this process (unless ``workers`` or ``client`` is given).
    workers : int, optional
        Worker processes of the embedded LocalCluster (0: one per core).
    variant : str, optional
        Mitsuba variant of the references (default ``[distributed] mitsuba_variant``).
    client : distributed.Client, optional
        An open Dask client to render on.
    config : DistributedConfig, optional
        Cluster, retry and clean-up settings (default ``[distributed]``).

    Returns
    -------
    Dataset
        Complete: every candidate view rendered or rejected, splits and manifest written.

    Raises
    ------
    DatasetWriteError
        The dataset folder cannot be written; nothing was changed.
    kdtrace.resources.InsufficientMemoryError
        Rendering one view in this process (:func:`view_memory_bytes`) would not fit in the
        memory available; nothing was rendered.
    kdtrace.distributed.UnitError
        A view failed on a worker (after retries); finished views are kept.

    Notes
    -----
    One view is one unit of work (:func:`make_view`): resumable and shareable, views
    already on disk with this dataset's key are not rendered again, and a complete
    manifest makes the call a pure cache hit. In-process and on Dask the arrays are
    identical (same seeds). The manifest records per view the worker that rendered it
    and its seconds.
    """
    from kdtrace.scenes import load_scene

    profile = resolve_profile(profile)
    scene = load_scene(scene) if isinstance(scene, str) else scene
    key = dataset_key(scene, profile)
    root = dataset_dir(scene, profile)
    manifest_path = root / "manifest.json"
    if manifest_path.is_file():
        try:
            manifest = json.loads(manifest_path.read_text())
        except (OSError, ValueError):
            manifest = None
        if manifest is not None and manifest.get("key") == key:
            return Dataset(root, manifest)
    check_writable(root)
    settings = config or DEFAULT_CONFIG.distributed
    variant = variant or settings.mitsuba_variant or None
    views = candidate_views(scene, profile)
    check_disk_space(root, len(views) - len(list(root.glob("view-*.npz"))), profile)
    distributed = client is not None or workers is not None or bool(scheduler or os.environ.get("KDTRACE_SCHEDULER"))
    if distributed:
        records = _render_distributed(scene, profile, views, root, key, variant,
                                      {"scheduler": scheduler, "client": client, "workers": workers,
                                       "progress": progress, "config": settings})
    else:
        require_memory(view_memory_bytes(profile), f"a {profile.width}x{profile.height} view of the dataset in {root}",
                       "choose a smaller width and height")
        disable = None if progress is None else not progress
        records = [make_view(scene, profile, view.index, root, key, variant)
                   for view in tqdm(views, desc=f"dataset {scene.name}", unit="view", disable=disable)]
    remove_stale_temporaries(root, settings.stale_temporary_seconds)
    records = [{name: value for name, value in record.items() if name != "key"} for record in records]
    accepted = [record["name"] for record in records if record["accepted"]]
    manifest = {
        "key": key, "recipe_version": RECIPE_VERSION, "scene": scene.name, "scene_hash": scene.content_hash(),
        "settings": {name: getattr(profile, name) for name in DATASET_FIELDS},
        "movement_region": [region.tolist() for region in movement_region(scene, profile.region_fraction)],
        "views": records, "splits": split_views(accepted, profile),
        "provenance": stamp(dataclasses.asdict(profile)),
    }
    encoded = json.dumps(manifest, indent=1)
    atomic_write_bytes(manifest_path, encoded.encode())
    return Dataset(root, json.loads(encoded))  # as a later cache hit reads it (tuples become lists)


def _render_distributed(scene: Scene, profile: ReconstructionProfile, views: list[ViewSpec], root: Path, key: str,
                        variant: str | None, options: dict[str, Any]) -> list[dict[str, Any]]:
    """Records of every view; the views not yet on disk are rendered as Dask units (``options``: of run_units)."""
    from kdtrace.distributed import Unit, run_units

    records: dict[int, dict[str, Any]] = {}
    for view in views:
        metadata = _view_metadata(root / f"{view.name}.npz")
        if metadata is not None and metadata.get("key") == key:
            records[view.index] = metadata
    missing = [Unit(f"{root.name}-{view.name}", (profile, view.index, str(root), key, variant))
               for view in views if view.index not in records]
    for unit, result in zip(missing, run_units(missing, make_view, shared=scene, description=f"dataset {scene.name}",
                                               **options), strict=True):
        records[unit.args[1]] = result.value
    return [records[view.index] for view in views]


# ------------------------------------------------------------------ crops
def _crop_corners(shape: tuple[int, int], size: int, count: int, rng: np.random.Generator) -> np.ndarray:
    height, width = shape
    if size > min(height, width):
        raise ValueError(f"crop size {size} exceeds the image ({height}x{width})")
    return np.stack([rng.integers(0, height - size + 1, count), rng.integers(0, width - size + 1, count)], axis=1)


def crops(dataset: Dataset, split: str, crop_size: int, crops_per_view: int, seed: int,
          buffers: tuple[str, ...] = tuple(BUFFERS)) -> dict[str, np.ndarray]:
    """Random square crops of the views of one split.

    Parameters
    ----------
    dataset : Dataset
    split : {"train", "validation", "test"}
    crop_size, crops_per_view : int
        Side of the crops (pixels) and how many per view.
    seed : int
        Crop positions depend only on it and the view index.
    buffers : tuple of str
        Which of :data:`BUFFERS` to return.

    Returns
    -------
    dict of str to ndarray
        Buffer name -> float32 (N, C, crop_size, crop_size), N = views x crops_per_view,
        linear values as rendered.

    Raises
    ------
    ValueError
        The split has no views, or the crop is larger than the views.
    kdtrace.resources.InsufficientMemoryError
        The views (held whole until their crops are stacked) and the crops would not fit in
        the memory available; nothing was loaded.
    """
    names = dataset.views(split)
    if not names:
        raise ValueError(f"dataset {dataset.root} has no {split} views")
    # every view stays whole in memory until the crops cut from it are stacked
    settings = dataset.manifest["settings"]
    channels = sum(BUFFERS[name] for name in buffers)
    whole_views = len(names) * settings["width"] * settings["height"] * sum(BUFFERS.values()) * 4
    stacked = len(names) * crops_per_view * crop_size * crop_size * channels * 4
    require_memory(whole_views + stacked, f"{crops_per_view} crops of {crop_size}x{crop_size} from each of the "
                   f"{len(names)} {split} views of {dataset.root}", "use fewer views or crops")
    out: dict[str, list[np.ndarray]] = {name: [] for name in buffers}
    for name in names:
        view = dataset.load_view(name)
        rng = np.random.default_rng([seed, 4, int(name.split("-")[1])])
        for top, left in _crop_corners(view["noisy"].shape[:2], crop_size, crops_per_view, rng):
            for buffer in buffers:
                out[buffer].append(view[buffer][top:top + crop_size, left:left + crop_size].transpose(2, 0, 1))
    return {name: np.ascontiguousarray(np.stack(values), np.float32) for name, values in out.items()}


# ------------------------------------------------------------------ superresolution
def photo(name: str) -> np.ndarray:
    """A photograph bundled with scikit-image as linear RGB float32 (H, W, 3) in [0, 1]."""
    import skimage.data

    image = getattr(skimage.data, name)()
    if image.ndim != 3 or image.shape[2] < 3:
        raise ValueError(f"skimage.data.{name} is not an RGB photograph")
    return srgb_decode(image[..., :3] / 255.0)


def degrade(target: np.ndarray, method: str = "area") -> np.ndarray:
    """The network input for ``target``: 2x downsampling then bicubic 2x upsampling.

    Parameters
    ----------
    target : ndarray, float32, shape (N, C, H, W)
        H and W even.
    method : {"area", "bicubic"}
        Downsampling: 2x2 box mean, or antialiased bicubic (PyTorch).

    Returns
    -------
    ndarray, float32, shape (N, C, H, W)
        Upsampled with :func:`reconstruction.models.bicubic_upsample` (the inference
        path's bicubic) and clamped to [0, 1] as :func:`reconstruction.models.superresolve` does.
    """
    return _upsampled(_halved(target, method))


def _halved(target: np.ndarray, method: str) -> np.ndarray:
    """:func:`halve` of (N, C, H, W) crops with even H and W, as float32 NumPy."""
    import torch

    if target.ndim != 4 or target.shape[2] % 2 or target.shape[3] % 2:
        raise ValueError(f"target must be (N, C, H, W) with even H and W, got {target.shape}")
    return halve(torch.from_numpy(np.ascontiguousarray(target, np.float32)), method).numpy()


def _upsampled(small: np.ndarray) -> np.ndarray:
    """The net's input from half-size crops: the inference path's bicubic 2x, clamped to [0, 1]."""
    import torch

    from reconstruction.models import bicubic_upsample

    return bicubic_upsample(torch.from_numpy(np.ascontiguousarray(small, np.float32)), 2).clamp(0.0, 1.0).numpy()


def degrade_displayed(target: np.ndarray, exposures: Any, method: str = "area") -> tuple[np.ndarray, np.ndarray]:
    """Display-referred superresolution pairs of linear crops: the net's input and its target, both displayed.

    Each crop is reduced 2x in linear radiance (what a render at half the resolution sees), the
    half-size crop and the crop are both shown with their image's exposure
    (:func:`reconstruction.metrics.to_display`: the tonemapping of the display-referred metrics),
    and the shown half-size crop is upsampled as :func:`degrade` upsamples.

    Parameters
    ----------
    target : ndarray, float32, shape (N, C, H, W)
        Linear radiance in [0, 1]; H and W even.
    exposures : sequence of float, length N
        Each crop's display exposure (its whole image's).
    method : {"area", "bicubic"}

    Returns
    -------
    inputs, targets : ndarray, float32, shape (N, C, H, W)
        In [0, 1], display-encoded.
    """
    from reconstruction.metrics import to_display

    if len(exposures) != len(target):
        raise ValueError(f"{len(exposures)} exposures for {len(target)} crops")
    small = _halved(target, method)

    def shown(crops: np.ndarray) -> np.ndarray:
        return np.stack([to_display(crop, e) for crop, e in zip(crops, exposures, strict=True)]).astype(np.float32)

    return _upsampled(shown(small)), shown(target)


def halve(tensor: Any, method: str = "area") -> Any:
    """2x downsampling of a float ``torch.Tensor`` (N, C, H, W), H and W even.

    Parameters
    ----------
    tensor : torch.Tensor
    method : {"area", "bicubic"}
        2x2 box mean (what a half-resolution render with a box filter sees), or
        antialiased bicubic (PyTorch).

    Returns
    -------
    torch.Tensor, shape (N, C, H/2, W/2)
    """
    import torch.nn.functional as F

    if method == "area":
        return F.avg_pool2d(tensor, 2)
    if method == "bicubic":
        return F.interpolate(tensor, scale_factor=0.5, mode="bicubic", align_corners=False, antialias=True)
    raise ValueError(f"unknown downsampling {method!r}; use 'area' or 'bicubic'")


def _image_crops(image: np.ndarray, size: int, count: int, rng: np.random.Generator) -> list[np.ndarray]:
    return [image[top:top + size, left:left + size].transpose(2, 0, 1)
            for top, left in _crop_corners(image.shape[:2], size, count, rng)]


#: Photo crops per training photo and requested crop when ``superres_augment`` is on (one per flip/rotation).
AUGMENT_FACTOR = 8
#: Range of the random exposure (linear scale) of augmented photo crops.
AUGMENT_EXPOSURE = (0.5, 1.5)


def augment(crop: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One random flip / 90-degree rotation (of 8) and exposure of a (C, S, S) crop, clipped to [0, 1]."""
    turned = np.rot90(crop, k=int(rng.integers(4)), axes=(1, 2))
    if rng.integers(2):
        turned = turned[:, :, ::-1]
    return np.clip(turned * rng.uniform(*AUGMENT_EXPOSURE), 0.0, 1.0)


def superres_data(profile: str | ReconstructionProfile = "quick",
                  datasets: list[Dataset] | tuple[Dataset, ...] = (),
                  space: str = "linear") -> dict[str, dict[str, np.ndarray]]:
    """Superresolution pairs: photo and render crops, per split.

    Parameters
    ----------
    profile : str or ReconstructionProfile
        Supplies ``superres_crop_size``, ``superres_crops_per_image``, ``superres_downsample``,
        ``superres_augment`` (training photos only: see :func:`augment`) and ``seed``.
    datasets : sequence of Dataset
        Precision Graphics datasets whose references add render crops (train views to
        train, validation views to validation, test views to test).
    space : {"linear", "display"}
        ``"linear"``: radiance clipped to [0, 1]; ``"display"``: each crop shown with its
        image's exposure (:func:`reconstruction.metrics.display_exposures` of the clipped photos
        and views of its split; :func:`degrade_displayed`).

    Returns
    -------
    dict
        Split -> {"input": bicubic-upsampled RGB, "target": RGB}, float32 (N, 3, S, S),
        in ``space``; ``test`` holds renders only and is absent without ``datasets``.

    Raises
    ------
    ValueError
        A crop does not fit an image.
    """
    from reconstruction.metrics import display_exposures
    from reconstruction.models import SUPERRES_SPACES

    if space not in SUPERRES_SPACES:
        raise ValueError(f"unknown superresolution space {space!r}; use one of {', '.join(SUPERRES_SPACES)}")
    profile = resolve_profile(profile)
    size, count = profile.superres_crop_size, profile.superres_crops_per_image
    rng = np.random.default_rng([profile.seed, 5])
    augment_rng = np.random.default_rng([profile.seed, 6])
    # per split: each source image (clipped, linear) and its crops
    sources: dict[str, list[tuple[np.ndarray, list[np.ndarray]]]] = {split: [] for split in SPLITS}
    for split, names in (("train", TRAIN_PHOTOS), ("validation", VALIDATION_PHOTOS)):
        for name in names:
            image = photo(name)
            image_crops = _image_crops(image, size, count, rng)
            if split == "train" and profile.superres_augment:
                # a stream of its own, so that every other crop is the same with and without augmentation
                extra = _image_crops(image, size, count * (AUGMENT_FACTOR - 1), augment_rng)
                image_crops = [augment(c, augment_rng) for c in image_crops + extra]
            sources[split].append((image, image_crops))
    for dataset in datasets:
        for split in SPLITS:
            for name in dataset.views(split):
                reference = dataset.load_view(name)["reference"]
                sources[split].append((reference, _image_crops(reference, size, count, rng)))
    out = {}
    for split, images in sources.items():
        if not any(crops_ for _, crops_ in images):
            continue
        target = np.clip(np.stack([c for _, crops_ in images for c in crops_]), 0.0, 1.0).astype(np.float32)
        if space == "linear":
            out[split] = {"input": degrade(target, profile.superres_downsample), "target": target}
            continue
        # an augmented crop keeps its photo's exposure: its own brightness change is the augmentation
        shown_with = display_exposures([np.clip(image, 0.0, 1.0) for image, _ in images])[1]
        exposures = [e for e, (_, crops_) in zip(shown_with, images, strict=True) for _ in crops_]
        inputs, shown = degrade_displayed(target, exposures, profile.superres_downsample)
        out[split] = {"input": inputs, "target": shown}
    return out
