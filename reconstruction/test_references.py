"""Cleaner references for a dataset's test views, where its reference noise would move the scores.

A dataset's references carry their own Monte Carlo noise (``reference_spp`` samples per pixel).
On the easiest test views the best denoisers come within a few dB of it (README: 1.28 dB on
Crytek Sponza's worst test view at 512 spp), so the noise moves the PSNR measured against them
by more than the 1 dB the tables may be off. Rendering every view of such a scene with more
samples would change the dataset, every model's training targets and every model's key; only
the test views are scored, so only they are refined, to the profile's
:meth:`~kdtrace.config.ReconstructionProfile.test_reference_spp`:

* the ``total - reference_spp`` extra samples are a Mitsuba render of the view's camera with
  an independent seed (:func:`refinement_seed`), on one Dr.Jit thread as the dataset's
  references are (reproducible to the bit);
* the refined reference is the sample-weighted mean ``(reference_spp * reference + extra *
  render) / total``: Mitsuba's film uses a box filter, so that is exactly a ``total``-spp
  estimate of the same image.

Refined references are kept in ``<dataset>/test-references-<total>spp/view-NNNN.npz`` under a
content key of the dataset, the total and the seed. One view is one unit of work, written
atomically, so an interrupted refinement resumes and concurrent workers leave one complete file;
with a Dask scheduler the views render on its workers. Training and validation data, their hash
and every model are untouched; the error-against-time sweep has references of its own.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from kdtrace.cache import content_key, load_npz, save_npz
from kdtrace.config import DEFAULT_CONFIG, DistributedConfig, ReconstructionProfile
from kdtrace.scene import Scene
from reconstruction.data import Dataset, DatasetWriteError, _view_metadata, check_writable, reference_variant, view_camera

#: Bump when the refinement recipe changes (invalidates every refined reference).
REFINEMENT_VERSION = 1


def refinement_seed(reference_seed: int, total_spp: int) -> int:
    """Mitsuba seed of a view's extra samples, independent of its noisy and reference seeds."""
    return int(np.random.SeedSequence([reference_seed, 3, total_spp]).generate_state(1)[0])


def refinement_key(dataset_key: str, total_spp: int) -> str:
    """Content key of a dataset's test references refined to ``total_spp``."""
    return content_key("test-references", REFINEMENT_VERSION, dataset_key, total_spp)


def refinement_dir(dataset: Dataset, total_spp: int) -> Path:
    """Folder of ``dataset``'s test references refined to ``total_spp`` samples per pixel."""
    return dataset.root / f"test-references-{total_spp}spp"


def _current_metadata(path: Path, key: str) -> dict[str, Any] | None:
    """The record of the refined view at ``path`` if it holds ``key``; None if missing, corrupt or stale.

    Reads the record only (``data._view_metadata``), not the arrays: the resume checks need the key.
    """
    metadata = _view_metadata(path)
    return metadata if metadata is not None and metadata.get("key") == key else None


def refine_view(scene: Scene, profile: ReconstructionProfile, record: dict[str, Any], base_reference: np.ndarray,
                folder: str | Path, key: str, total_spp: int, variant: str | None = None) -> dict[str, Any]:
    """Refine one test view's reference into ``folder/NAME.npz``, unless it is there: a unit of work.

    Parameters
    ----------
    scene : Scene
    profile : ReconstructionProfile
        The dataset's profile (resolution, path length, ``reference_spp``).
    record : dict
        The view's record in the dataset manifest (name, camera, reference seed).
    base_reference : ndarray
        The dataset's reference of the view, (H, W, 3) float32 linear radiance.
    folder : str or Path
    key : str
        :func:`refinement_key` of the dataset and ``total_spp``.
    total_spp : int
        Samples per pixel of the refined reference (> ``profile.reference_spp``).
    variant : str, optional
        Mitsuba variant (see :func:`reconstruction.data.reference_variant`).

    Returns
    -------
    dict
        The file's metadata: key, name, spp, seed, render seconds and Mitsuba variant.
    """
    # the dataset's own context manager: its references are rendered on one thread to be reproducible
    from reconstruction.data import _one_jit_thread
    from references.llvm import activate_variant
    from references.mitsuba import render_reference

    path = Path(folder) / f"{record['name']}.npz"
    metadata = _current_metadata(path, key)
    if metadata is not None:
        return metadata
    extra = total_spp - profile.reference_spp
    seed = refinement_seed(int(record["reference_seed"]), total_spp)
    started = time.perf_counter()
    variant = activate_variant(reference_variant(variant))
    with _one_jit_thread():
        render = render_reference(dataclasses.replace(scene, cameras=[view_camera(record)]), spp=extra,
                                  max_depth=profile.max_depth, seed=seed, width=profile.width,
                                  height=profile.height, cache=False, variant=variant)
    refined = (profile.reference_spp * base_reference.astype(np.float64) + extra * render.rgb) / total_spp
    metadata = {"key": key, "name": record["name"], "spp": total_spp, "base_spp": profile.reference_spp,
                "extra_spp": extra, "extra_seed": seed, "reference_variant": render.variant,
                "seconds": time.perf_counter() - started}
    try:
        save_npz(path, {"reference": np.ascontiguousarray(refined, np.float32)}, metadata)
    except OSError as error:
        raise DatasetWriteError(error.errno, f"cannot write {path}: {error.strerror or error}; nothing half-written "
                                "was left") from error
    return json.loads(json.dumps(metadata))


@dataclasses.dataclass(frozen=True)
class RefinedDataset:
    """A dataset whose test views load their refined reference; every other view as stored.

    Attributes
    ----------
    dataset : Dataset
    total_spp : int
        Samples per pixel of the test views' references (the dataset's own when not refined).
    folder : Path or None
        Where the refined references are; None when the test views keep the dataset's.
    refinement_key : str
        :func:`refinement_key` the refined files must carry.
    """

    dataset: Dataset
    total_spp: int
    folder: Path | None = None
    refinement_key: str = ""

    @property
    def key(self) -> str:
        """The dataset's content key (the refined references do not change its training data)."""
        return self.dataset.key

    @property
    def root(self) -> Path:
        """The dataset's folder."""
        return self.dataset.root

    @property
    def manifest(self) -> dict[str, Any]:
        """The dataset's manifest."""
        return self.dataset.manifest

    def views(self, split: str | None = None) -> list[str]:
        """Names of the accepted views, all or those of one split (as :meth:`Dataset.views`)."""
        return self.dataset.views(split)

    def reference_spp(self, split: str) -> int:
        """Samples per pixel of the references of ``split``'s views."""
        return self.total_spp if split == "test" else self.dataset.manifest["settings"]["reference_spp"]

    def load_view(self, name: str) -> dict[str, np.ndarray]:
        """A view's buffers (as :meth:`Dataset.load_view`), a test view's ``reference`` refined.

        Raises
        ------
        ValueError
            The view, or a test view's refined reference, is missing, corrupt or of another key.
        """
        arrays = self.dataset.load_view(name)
        if self.folder is not None and name in self.dataset.manifest["splits"]["test"]:
            path = self.folder / f"{name}.npz"
            loaded = load_npz(path)
            if loaded is None or loaded[1].get("key") != self.refinement_key:
                raise ValueError(f"{path} is missing, corrupt or not a refined reference of this dataset")
            if loaded[0]["reference"].shape != arrays["reference"].shape:
                raise ValueError(f"{path} holds a {loaded[0]['reference'].shape} reference, the view "
                                 f"{arrays['reference'].shape}")
            arrays = {**arrays, "reference": loaded[0]["reference"]}
        return arrays


def refine_test_references(dataset: Dataset, scene: Scene, profile: ReconstructionProfile,
                           progress: bool | None = None, *, scheduler: str | None = None, workers: int | None = None,
                           client: Any = None, variant: str | None = None,
                           config: DistributedConfig | None = None) -> RefinedDataset:
    """``dataset`` with its test views' references refined to the profile's spp for ``scene``.

    Parameters
    ----------
    dataset : Dataset
        The scene's dataset under ``profile`` (:func:`reconstruction.data.generate_dataset`).
    scene : Scene
    profile : ReconstructionProfile
        Its :meth:`~kdtrace.config.ReconstructionProfile.test_reference_spp` for the scene
        sets the total; at ``reference_spp`` nothing is rendered (the scene does not need it).
    progress : bool, optional
        Show a tqdm bar (None: only on a terminal).
    scheduler, workers, client, config
        As in :func:`reconstruction.data.generate_dataset`: render the views as Dask units.
    variant : str, optional
        Mitsuba variant (default ``[distributed] mitsuba_variant``).

    Returns
    -------
    RefinedDataset
        Every test view's refined reference on disk (or none needed).

    Raises
    ------
    ValueError
        ``dataset`` is not the scene's under ``profile``, or its references are not Mitsuba's.
    DatasetWriteError
        The folder cannot be written; finished views are kept.
    """
    from reconstruction.data import dataset_key

    total = profile.test_reference_spp(scene.name)
    if total == profile.reference_spp:
        return RefinedDataset(dataset, total)
    if dataset.key != dataset_key(scene, profile):
        raise ValueError(f"{dataset.root} is not {scene.name}'s dataset under this profile")
    if profile.reference != "mitsuba":
        raise ValueError("test references are refined with Mitsuba; this profile's references are "
                         f"{profile.reference!r}")
    key = refinement_key(dataset.key, total)
    folder = refinement_dir(dataset, total)
    check_writable(folder)
    settings = config or DEFAULT_CONFIG.distributed
    variant = variant or settings.mitsuba_variant or None
    records = {record["name"]: record for record in dataset.manifest["views"]}
    missing = [name for name in dataset.views("test") if _current_metadata(folder / f"{name}.npz", key) is None]
    if missing and (client is not None or workers is not None or scheduler or os.environ.get("KDTRACE_SCHEDULER")):
        from kdtrace.distributed import Unit, run_units

        units = [Unit(f"{folder.parent.name}-{folder.name}-{name}",
                      (profile, records[name], dataset.load_view(name)["reference"], str(folder), key, total, variant))
                 for name in missing]
        run_units(units, refine_view, scheduler, client=client, shared=scene, workers=workers, progress=progress,
                  description=f"test references {scene.name}", config=settings)
    else:
        disable = None if progress is None else not progress
        for name in tqdm(missing, desc=f"test references {scene.name} ({total} spp)", unit="view", disable=disable):
            refine_view(scene, profile, records[name], dataset.load_view(name)["reference"], folder, key, total,
                        variant)
    return RefinedDataset(dataset, total, folder, key)
