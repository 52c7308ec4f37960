"""Run time against error: our pipelines against brute-force Mitsuba.

For each reconstruction scene of a profile, at ``sweep_width`` x ``sweep_height`` from the
scene's default camera, the error of five methods against a Mitsuba reference of
``sweep_reference_spp`` samples per pixel, as a function of wall-clock seconds:

``kdtrace``
    our path tracer alone (local-branch tree, no auxiliary buffers), at each ``sweep_spp``;
``mitsuba``
    Mitsuba 3's ``path`` integrator alone, at each ``sweep_spp`` (the scene converted and
    loaded beforehand; one warm-up render at the same spp, so JIT compilation is never
    timed; the render and the copy to NumPy are timed);
``kdtrace+denoiser``
    our path tracer (with albedo) + the scene's own denoiser (Precision Graphics);
``kdtrace-half+denoiser+superres``
    our path tracer at half resolution + the denoiser + 2x superresolution;
``kdtrace+oidn``
    our path tracer (with albedo and normal) + Open Image Denoise;
``kdtrace+denoiser-blend``
    the documented variant that never loses to its input: the denoised frame blended with
    the noisy one, ``w * denoised + (1 - w) * noisy``, ``w = min(w(spp), cap)`` with ``w(spp)``
    fitted per spp on the scene's validation views and, at spp >= 2, ``cap`` the frame's own
    bound from two halves of its samples (:mod:`reconstruction.blend`; the halves are timed
    as its render, the cap's two denoiser passes as reconstruction; the ``weight`` and
    ``frame_cap`` columns record both);
``kdtrace+demodulated``, ``mitsuba+demodulated``
    either renderer (with albedo) + the scene's albedo-demodulated denoiser, the documented
    variant of the paper's network (``Denoiser(demodulate=True)``, same parameters), on the
    scenes of the profile's ``demodulated_scenes``;
``kdtrace+perceptual``, ``mitsuba+perceptual``
    the same with the scene's perceptual denoiser (``Denoiser(perceptual=G)``, trained in a
    display-like transfer), on the scenes of the profile's ``perceptual_scenes``;
``mitsuba+denoiser``, ``mitsuba+oidn``
    Mitsuba's ``path`` integrator wrapped in its ``aov`` integrator (RGB plus albedo and
    shading normal in one render, timed as a whole) + our per-scene denoiser / OIDN: the
    reconstruction's contribution measured on the fastest renderer too. Mitsuba's albedo
    AOV is the BSDF albedo at the first hit (mirrors and glass included), which is what our
    renderer's albedo buffer holds on diffuse surfaces; the networks were trained on ours.

Plug-in denoisers (``kdtrace report --denoiser SPEC``, :mod:`reports.plugins`) add the method
``kdtrace+SPEC``: our path tracer with albedo and normal + the plug-in, measured as
``kdtrace+oidn`` (:func:`measure_plugin_scene`), in every table, the plots and the headline.

Seconds of a pipeline = render + reconstruction, warm: our render time is the kernel's
wall time (``RenderResult.seconds``: scene packing and kernel compilation excluded); a
reconstruction step is timed after one warm-up call on the same input. Every timing is
the shortest of :data:`TIMING_REPEATS` runs. Errors: relMSE on the HDR images and PSNR on
the linear images clipped to [0, 1] (:mod:`reconstruction.metrics`; the superresolution
output is itself clipped to [0, 1], so its relMSE includes the clipping of pixels
brighter than 1).

From the curves: an equal-time table (each method's error at common seconds,
interpolated piecewise linearly in log-log for relMSE and in PSNR over log seconds,
"—" outside a method's measured range), an equal-error table (the seconds each method
needs to reach a threshold; "≤ s" when its fastest point already does, "not reached"
when no measured point does — never extrapolated) and the headline speed-up of our
pipeline over Mitsuba at equal error.

Rows are measured per scene and cached in ``OUT_DIR/rows/error_time/SCENE.json`` with a
content key; a rerun reuses them (and says so), ``fresh=True`` measures again. Plug-in rows
are cached apart, in ``OUT_DIR/rows/error_time-plugins/SCENE/``.

This module measures and holds the entry points (:func:`generate`, :func:`main`); the curve
maths are in :mod:`reports.error_time_curves`, the plots and Markdown in
:mod:`reports.error_time_present`.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from tqdm import tqdm

from kdtrace.allocator import freed_memory_retained
from kdtrace.cache import atomic_write_bytes, content_key
from kdtrace.config import Config, ProfileConfig, ReconstructionProfile
from kdtrace.timing import TIMING_REPEATS, shortest
from reconstruction.metrics import RELMSE_EPSILON
from reports.error_time_curves import all_measured, plugin_method
from reports.error_time_present import write_outputs
from reports.metrics import Metric, write_metrics
from reports.notes import ReportNote

#: Bump when what a row measures changes: cached rows become stale.
ROW_VERSION = 7

#: Table 2's documented denoiser variants (:data:`reports.reconstruction_tables.DENOISER_VARIANTS`, by key)
#: that the sweep measures beside the paper's network.
SWEEP_VARIANTS = ("demodulated", "perceptual")


def _variants() -> dict:
    """Key -> :class:`reports.reconstruction_tables.DenoiserVariant` of each of :data:`SWEEP_VARIANTS`."""
    from reports.reconstruction_tables import DENOISER_VARIANTS

    return {variant.key: variant for variant in DENOISER_VARIANTS if variant.key in SWEEP_VARIANTS}


def sweep_variants(profile: ProfileConfig) -> dict[str, tuple[str, ...]]:
    """The report profile's scenes of each of :data:`SWEEP_VARIANTS` (``demodulated_scenes``, ``perceptual_scenes``)."""
    return {key: tuple(getattr(profile, variant.scenes_field)) for key, variant in _variants().items()}
#: Bump when what a plug-in denoiser's row measures changes.
PLUGIN_ROW_VERSION = 1






# ------------------------------------------------------------------ measuring
@dataclass
class Reconstruction:
    """The trained networks of one profile: a denoiser per scene and the superresolution net."""

    denoisers: dict[str, Any]
    superres: Any
    blends: dict[str, Any] = dataclasses.field(default_factory=dict)
    #: A documented variant of the denoiser (a key of :data:`SWEEP_VARIANTS`) -> scene -> its model.
    variants: dict[str, dict[str, Any]] = dataclasses.field(default_factory=dict)

    @classmethod
    def load(cls, scene_names: Sequence[str], profile: ReconstructionProfile, all_scenes: Sequence[str],
             progress: bool = True, blend_spp: Sequence[int] = (),
             variant_scenes: Mapping[str, Sequence[str]] | None = None) -> Reconstruction:
        """Train (or reuse from the cache) the denoiser of each of ``scene_names`` and the SR net.

        The superresolution net is trained on the photographs plus the renders of
        ``all_scenes`` (the profile's reconstruction scenes), as for Table 5. With
        ``blend_spp``, each denoiser's blend weights at those spp are fitted (or reused) on
        its scene's validation views (:func:`reconstruction.blend.fit_blend_weights`).
        ``variant_scenes`` maps a key of :data:`SWEEP_VARIANTS` to the scenes that also get
        that variant of their denoiser (Table 2's variants, the same cached models).
        """
        from kdtrace.scenes import load_scene
        from reconstruction.blend import fit_blend_weights
        from reconstruction.data import generate_dataset
        from reconstruction.train import train_denoiser, train_superres

        denoisers = {name: train_denoiser([name], profile, progress=progress).model for name in scene_names}
        superres = train_superres(profile, list(all_scenes), progress=progress).model
        blends = {}
        if blend_spp:
            for name, model in denoisers.items():
                blends[name] = fit_blend_weights(model, generate_dataset(name, profile, progress=False),
                                                 load_scene(name), blend_spp, profile.max_depth, profile.seed,
                                                 progress=progress)
        known = _variants()
        variants = {key: {name: train_denoiser([name], profile, progress=progress,
                                               **known[key].train_options(profile)).model for name in names}
                    for key, names in (variant_scenes or {}).items() if names}
        return cls(denoisers, superres, blends, variants)


def denoise_frame(model, frame) -> np.ndarray:
    """Our denoiser on a :class:`~kdtrace.render.RenderResult` with albedo (whole frame, float32)."""
    from reconstruction.inference import denoise

    return denoise(model, frame.rgb, frame.albedo)


def superresolve_frame(model, denoised: np.ndarray) -> np.ndarray:
    """2x superresolution of a denoised linear frame, clipped to [0, 1] first (the SR net's domain)."""
    from reconstruction.models import superresolve

    return superresolve(model, np.clip(denoised, 0.0, 1.0))


def timed_reconstruction(steps: Sequence[Callable[[Any], Any]], frame: Any, repeats: int = TIMING_REPEATS) -> tuple[Any, list[float]]:
    """Run a chain of reconstruction steps on ``frame``; each step warm and timed on its own input.

    Returns
    -------
    (object, list of float)
        The last step's output and the shortest seconds of each step.
    """
    seconds = []
    current = frame
    for step in steps:
        current, elapsed = shortest(lambda step=step, value=current: step(value), repeats)
        seconds.append(elapsed)
    return current, seconds


def errors(image: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """The :data:`ERRORS` of ``image`` against ``reference``: ``psnr`` (dB, linear clipped to [0, 1]),
    ``relmse`` (HDR), ``display_psnr`` (dB) and ``flip`` of the displayed images (the reference's
    exposure, :func:`reconstruction.metrics.display_metrics`)."""
    from reconstruction.metrics import display_metrics, psnr, relmse

    shown = display_metrics(image, reference, name="the sweep's reference")
    return {"psnr": psnr(image, reference), "relmse": relmse(image, reference), "display_psnr": shown["display_psnr"],
            "flip": shown["flip"]}


def reference_floor(reference) -> dict[str, float]:
    """The reference's own noise: expected relMSE and the PSNR its variance alone would give.

    Errors near these values measure the reference's noise, not the method's. PSNR is
    computed on images clipped to [0, 1], so only pixels whose reference lies inside
    (0, 1) count towards its noise (clipping hides the rest).
    """
    rgb = reference.rgb.astype(np.float64)
    variance = reference.variance.astype(np.float64)
    floor = float(np.mean(variance / (rgb * rgb + RELMSE_EPSILON)))
    mse = float(np.mean(np.where((rgb > 0.0) & (rgb < 1.0), variance, 0.0)))
    return {"relmse_floor": floor, "psnr_ceiling": math.inf if mse == 0 else -10.0 * math.log10(mse)}


def mitsuba_seed(seed: int, spp: int) -> int:
    """A 32-bit Mitsuba sampler seed of the sweep at ``spp`` (hashed: independent of the reference's passes)."""
    return int(content_key("error-time-mitsuba", seed, spp)[:8], 16)


class MitsubaTimer:
    """Mitsuba's ``path`` integrator on one scene, converted once, rendered warm.

    Parameters
    ----------
    scene : Scene
    max_depth, width, height : int
    """

    def __init__(self, scene, max_depth: int, width: int, height: int) -> None:
        from references.llvm import activate_variant

        self.variant = activate_variant(None)  # llvm_ad_rgb, or scalar_rgb with a warning
        import mitsuba as mi

        from references.mitsuba import to_mitsuba

        self._mi = mi
        self.scene, _ = to_mitsuba(scene, max_depth, width, height, 1)
        path = {"type": "path", "max_depth": int(max_depth)}
        self.integrator = mi.load_dict(path)
        self.aov_integrator = mi.load_dict({"type": "aov", "aovs": "albedo:albedo,normal:sh_normal", "integrator": path})

    def image(self, spp: int, seed: int, aov: bool = False) -> np.ndarray:
        """One render: ``mi.render`` and the copy to NumPy (which forces evaluation), float32.

        (H, W, 3) RGB; with ``aov`` (H, W, 9): RGB, albedo and shading normal.
        """
        integrator = self.aov_integrator if aov else self.integrator
        image = np.array(self._mi.render(self.scene, integrator=integrator, spp=int(spp), seed=int(seed)),
                         dtype=np.float32)
        return image[..., :9] if aov else image[..., :3]

    def render(self, spp: int, seed: int, aov: bool = False) -> tuple[np.ndarray, float]:
        """(image, shortest seconds) after one untimed warm-up render at the same spp (see :meth:`image`)."""
        return shortest(lambda: self.image(spp, seed, aov))

    @property
    def threads(self) -> int:
        """Dr.Jit's worker threads."""
        import drjit as dr

        return int(dr.thread_count())


@dataclass(frozen=True)
class AuxFrame:
    """A frame with the buffers the denoisers take (the fields of a RenderResult they read)."""

    rgb: np.ndarray
    albedo: np.ndarray
    normal: np.ndarray


def _point(method: str, spp: int, width: int, height: int, render_seconds: float,
           reconstruction_seconds: Sequence[float], image: np.ndarray, reference: np.ndarray,
           input_errors: dict[str, float] | None = None, **extra: float) -> dict[str, Any]:
    """One measured point; a reconstruction's also records its noisy input's :func:`errors` (``input_psnr``, ...)."""
    point = {"method": method, "spp": int(spp), "width": int(width), "height": int(height),
             "paths": int(width * height * spp), "render_seconds": float(render_seconds),
             "reconstruction_seconds": float(sum(reconstruction_seconds)),
             "seconds": float(render_seconds + sum(reconstruction_seconds)), **errors(image, reference)}
    for key, value in (input_errors or {}).items():
        point[f"input_{key}"] = float(value)
    return {**point, **{key: float(value) for key, value in extra.items()}}


def measure_scene(name: str, config: Config, profile_name: str, models: Reconstruction,
                  progress: tqdm | None = None) -> dict[str, Any]:
    """Measure every method at every ``sweep_spp`` on one scene (see the module docstring).

    Returns
    -------
    dict
        ``scene``, ``triangles``, ``width``, ``height``, ``reference`` (spp, seconds,
        variant, noise floor), ``points`` (one dict per method and spp: seconds split
        into render and reconstruction, ``psnr``, ``relmse``), thread counts and warnings.
    """
    from kdtrace.kdtree import build_kdtree
    from kdtrace.render import render
    from kdtrace.scenes import load_scene
    from reconstruction.baselines import oidn
    from references.mitsuba import render_reference

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    width, height, depth = profile.sweep_width, profile.sweep_height, recon.max_depth
    if width % 2 or height % 2:
        raise ValueError(f"sweep_width/height must be even for the half-resolution pipeline, got {width}x{height}")

    def status(text: str) -> None:
        if progress is not None:
            progress.set_postfix_str(f"{name}: {text}")

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(name)
        tree = build_kdtree(scene, "local", config.kdtree)
        status(f"reference {profile.sweep_reference_spp} spp")
        reference = render_reference(scene, profile.sweep_reference_spp, depth, profile.seed % 2**32, width, height)
        mitsuba = MitsubaTimer(scene, depth, width, height)
        denoiser, superres = models.denoisers[name], models.superres

        def ours(spp: int, w: int, h: int, aux: bool, first_sample: int = 0):
            return shortest(lambda: render(scene, spp=spp, max_depth=depth, seed=profile.seed, width=w, height=h,
                                           aux=aux, tree=tree, first_sample=first_sample),
                            warmup=0, seconds_of=lambda r: r.seconds)

        def blended(weights, model, spp: int, frame, denoised, denoise_steps, render_seconds):
            """The blend pipeline at ``spp``: (image, render seconds, step seconds, weight, frame cap or NaN).

            At spp >= 2 the frame is rendered as two halves of its samples, which give the
            frame back (the same samples as ``frame``, so its denoised image is reused) and
            the frame's own weight cap (:func:`reconstruction.blend.frame_weight_cap`).
            """
            from reconstruction.blend import combine_halves, frame_weight_cap
            from reconstruction.inference import denoise

            if spp < 2:
                image, steps = timed_reconstruction([lambda d: weights.apply(frame.rgb, d, spp)], denoised)
                return image, render_seconds, denoise_steps + steps, weights.weight(spp), math.nan
            first, first_seconds = ours(spp // 2, width, height, aux=True)
            second, second_seconds = ours(spp - spp // 2, width, height, aux=True, first_sample=spp // 2)
            rgb, albedo = combine_halves(first, second)
            if not (np.allclose(rgb, frame.rgb, rtol=1e-5, atol=1e-6) and np.allclose(albedo, frame.albedo, rtol=1e-5, atol=1e-6)):
                raise RuntimeError(f"{name} at {spp} spp: the two halves do not give the frame back")
            cap, cap_steps = timed_reconstruction(
                [lambda halves: frame_weight_cap(lambda c, a: denoise(model, c, a), *halves)], (first, second))
            image, steps = timed_reconstruction([lambda d: weights.apply(frame.rgb, d, spp, cap)], denoised)
            return (image, first_seconds + second_seconds, denoise_steps + cap_steps + steps, weights.weight(spp, cap),
                    cap)

        points = []
        for spp in profile.sweep_spp:
            status(f"{spp} spp")
            plain, seconds = ours(spp, width, height, aux=False)
            points.append(_point("kdtrace", spp, width, height, seconds, [], plain.rgb, reference.rgb))
            image, seconds = mitsuba.render(spp, mitsuba_seed(profile.seed, spp))
            points.append(_point("mitsuba", spp, width, height, seconds, [], image, reference.rgb))

            frame, frame_seconds = ours(spp, width, height, aux=True)
            frame_errors = errors(frame.rgb, reference.rgb)
            denoised, steps = timed_reconstruction([lambda f: denoise_frame(denoiser, f)], frame)
            points.append(_point("kdtrace+denoiser", spp, width, height, frame_seconds, steps, denoised, reference.rgb,
                                 frame_errors))
            if name in models.blends:
                image, blend_seconds, blend_steps, weight, cap = blended(models.blends[name], denoiser, spp, frame,
                                                                         denoised, steps, frame_seconds)
                points.append(_point("kdtrace+denoiser-blend", spp, width, height, blend_seconds, blend_steps, image,
                                     reference.rgb, frame_errors, weight=weight, frame_cap=cap))
            image, steps = timed_reconstruction([lambda f: oidn(f.rgb, f.albedo, f.normal)], frame)
            points.append(_point("kdtrace+oidn", spp, width, height, frame_seconds, steps, image, reference.rgb,
                                 frame_errors))

            buffers, mitsuba_seconds = mitsuba.render(spp, mitsuba_seed(profile.seed, spp), aov=True)
            mitsuba_frame = AuxFrame(buffers[..., :3], buffers[..., 3:6], buffers[..., 6:9])
            mitsuba_errors = errors(mitsuba_frame.rgb, reference.rgb)
            image, steps = timed_reconstruction([lambda f: denoise_frame(denoiser, f)], mitsuba_frame)
            points.append(_point("mitsuba+denoiser", spp, width, height, mitsuba_seconds, steps, image, reference.rgb,
                                 mitsuba_errors))
            image, steps = timed_reconstruction([lambda f: oidn(f.rgb, f.albedo, f.normal)], mitsuba_frame)
            points.append(_point("mitsuba+oidn", spp, width, height, mitsuba_seconds, steps, image, reference.rgb,
                                 mitsuba_errors))
            for key, trained in models.variants.items():
                if name not in trained:
                    continue
                for method, source, render_seconds, input_errors in (
                        (f"kdtrace+{key}", frame, frame_seconds, frame_errors),
                        (f"mitsuba+{key}", mitsuba_frame, mitsuba_seconds, mitsuba_errors)):
                    image, steps = timed_reconstruction([lambda f, model=trained[name]: denoise_frame(model, f)], source)
                    points.append(_point(method, spp, width, height, render_seconds, steps, image, reference.rgb,
                                         input_errors))

            half, seconds = ours(spp, width // 2, height // 2, aux=True)
            image, steps = timed_reconstruction([lambda f: denoise_frame(denoiser, f),
                                                 lambda d: superresolve_frame(superres, d)], half)
            point = _point("kdtrace-half+denoiser+superres", spp, width, height, seconds, steps, image, reference.rgb)
            point["paths"] = int(width // 2 * (height // 2) * spp)
            points.append(point)
    import torch

    return {
        "scene": name, "triangles": len(scene.triangles), "width": width, "height": height, "max_depth": depth,
        "reference": {"spp": reference.spp, "seconds": reference.seconds, "variant": reference.variant,
                      **reference_floor(reference)},
        "mitsuba_variant": mitsuba.variant, "mitsuba_threads": mitsuba.threads, "torch_threads": torch.get_num_threads(),
        "points": points, "warnings": sorted({str(w.message) for w in caught}),
        **({"blend": blend_record(models.blends[name])} if name in models.blends else {}),
    }


def blend_record(weights) -> dict[str, Any]:
    """A row's record of the fitted blend weights: ``spp``, ``weights``, ``views``, ``by_space``, ``limited_by``."""
    return {**dataclasses.asdict(weights), "limited_by": [weights.limiting_space(spp) for spp in weights.spp]}


#: Reconstruction profile fields the sweep's and §6.4's rows do not depend on: the datasets'
#: refined test references (those rows have Mitsuba references of their own).
ROW_INDEPENDENT_FIELDS = ("test_reference_spp_by_scene",)


def row_settings(config: Config, profile: ProfileConfig, recon: ReconstructionProfile) -> list[dict]:
    """The settings in a sweep or §6.4 row's key: the report, reconstruction, tree and render settings."""
    recon_settings = {name: value for name, value in dataclasses.asdict(recon).items()
                      if name not in ROW_INDEPENDENT_FIELDS}
    return [dataclasses.asdict(profile), recon_settings, dataclasses.asdict(config.kdtree),
            dataclasses.asdict(config.render)]


def measure_plugin_scene(name: str, spec: str, config: Config, profile_name: str,
                         progress: tqdm | None = None) -> dict[str, Any]:
    """The plug-in denoiser ``spec`` after our path tracer at every ``sweep_spp`` on one scene.

    Measured as ``kdtrace+oidn`` is in :func:`measure_scene`: the same frame (our render
    with albedo and normal, same seed; its kernel seconds, shortest of
    :data:`TIMING_REPEATS`), the plug-in timed warm on float32 copies of the buffers, the
    same Mitsuba reference (from the cache when the sweep rendered it). A
    :class:`~kdtrace.plugins.PluginError` ends the row: it then holds ``failed``
    (``failed: MESSAGE``) and the points measured before.

    Returns
    -------
    dict
        ``scene``, ``plugin``, ``points`` (method :func:`plugin_method`), ``warnings``, maybe ``failed``.
    """
    from kdtrace.kdtree import build_kdtree
    from kdtrace.plugins import PluginError, load_denoiser
    from kdtrace.render import render
    from kdtrace.scenes import load_scene
    from references.mitsuba import render_reference
    from reports.plugins import failure

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    width, height, depth = profile.sweep_width, profile.sweep_height, recon.max_depth
    method = plugin_method(spec)
    row: dict[str, Any] = {"scene": name, "plugin": spec, "method": method, "points": []}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scene = load_scene(name)
        tree = build_kdtree(scene, "local", config.kdtree)
        reference = render_reference(scene, profile.sweep_reference_spp, depth, profile.seed % 2**32, width, height)
        try:
            denoiser = load_denoiser(spec)
            for spp in profile.sweep_spp:
                if progress is not None:
                    progress.set_postfix_str(f"{name}: plug-in {spec}, {spp} spp")
                result, seconds = shortest(lambda spp=spp: render(scene, spp=spp, max_depth=depth, seed=profile.seed,
                                                                  width=width, height=height, aux=True, tree=tree),
                                           warmup=0, seconds_of=lambda r: r.seconds)
                frame = AuxFrame(*(np.ascontiguousarray(a, np.float32) for a in (result.rgb, result.albedo, result.normal)))
                image, steps = timed_reconstruction([lambda f: denoiser(f.rgb, f.albedo, f.normal)], frame)
                row["points"].append(_point(method, spp, width, height, seconds, steps, image, reference.rgb,
                                            errors(frame.rgb, reference.rgb)))
        except PluginError as error:
            row["failed"] = failure(error)
    row["warnings"] = sorted({str(w.message) for w in caught})
    return row


def plugin_scene_rows(specs: Sequence[str], config: Config, profile_name: str, out_dir: Path, fresh: bool,
                      progress: bool) -> list[dict]:
    """:func:`measure_plugin_scene` of every plug-in on every reconstruction scene, cached apart from our rows.

    A row is kept in ``out_dir/rows/error_time-plugins/SCENE/SLUG.json`` under a content
    key of the spec, a hash of the plug-in's source, :data:`PLUGIN_ROW_VERSION` and the
    settings of :func:`scene_rows`; a failed row is measured again on the next run.
    """
    from kdtrace.plugins import DENOISER_GROUP
    from reports.plugins import fingerprint, slug

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    settings = row_settings(config, profile, recon)
    pairs = [(spec, name) for spec in specs for name in profile.reconstruction_scenes]
    rows = []
    bar = tqdm(pairs, unit="row", desc=f"error_time plug-ins ({profile_name})", disable=not progress)
    for spec, name in bar:
        path = out_dir / "rows" / "error_time-plugins" / name / f"{slug(spec)}.json"
        key = content_key("error_time-plugin-row", PLUGIN_ROW_VERSION, name, spec, fingerprint(spec, DENOISER_GROUP),
                          TIMING_REPEATS, settings)
        if not fresh and path.exists():
            saved = json.loads(path.read_text())
            if saved.get("key") == key and not saved["row"].get("failed"):
                bar.write(f"error_time {name}: reusing plug-in {spec}'s row measured {saved['measured_at']}")
                rows.append(saved["row"])
                continue
        row = measure_plugin_scene(name, spec, config, profile_name, bar)
        atomic_write_bytes(path, json.dumps({"key": key, "measured_at": time.strftime("%Y-%m-%d %H:%M:%S"), "row": row},
                                            indent=1).encode())
        rows.append(row)
    return rows


def with_plugins(rows: Sequence[dict], plugin_rows: Sequence[dict]) -> list[dict]:
    """Our rows (copies) with the plug-ins' points appended and their failures under ``plugin_failures``."""
    merged = []
    for row in rows:
        extra = [p for p in plugin_rows if p["scene"] == row["scene"]]
        merged.append({**row, "points": [*row["points"], *(point for p in extra for point in p["points"])],
                       "plugins": {p["plugin"]: p.get("failed") or "ok" for p in extra}})
    return merged


def scene_rows(kind: str, version: int, measure_scene: Callable[..., dict], config: Config, profile_name: str,
               out_dir: Path, fresh: bool, progress: bool, blend_spp: Sequence[int] = (),
               variant_scenes: Mapping[str, Sequence[str]] | None = None, networks: bool = True) -> list[dict]:
    """Per-scene rows of a report over the profile's reconstruction scenes, reused when their key matches.

    A row is cached in ``out_dir/rows/KIND/SCENE.json`` under a content key of the scene,
    ``version``, :data:`TIMING_REPEATS`, the report and reconstruction profiles, the
    KD-tree and render settings, and the source of the renderer and (with ``networks``) the
    source and stored weights of the networks (:func:`reconstruction.fingerprint.networks_fingerprint`).
    A reused row is announced with the date it was measured; each new row is written atomically
    as soon as it is measured, so an interrupted run resumes at the next unfinished scene. The networks
    (:class:`Reconstruction`) are trained or loaded only when some row must be measured.

    Parameters
    ----------
    kind : str
        Report name (folder of the rows, first part of the key).
    version : int
        The report's row version.
    measure_scene : callable
        ``measure_scene(name, config, profile_name, models, progress_bar) -> dict``.
    config, profile_name, out_dir, fresh, progress
        As for :func:`generate`.
    blend_spp : sequence of int
        Fit the denoisers' blend weights at these spp (:meth:`Reconstruction.load`); () skips it.
    variant_scenes : mapping, optional
        Denoiser variant -> scenes whose variant is loaded too (:meth:`Reconstruction.load`).
    networks : bool
        Load the networks for ``measure_scene``; False passes None (a report that renders only).

    Returns
    -------
    list of dict
        One row per scene, in the profile's order.
    """
    from kdtrace.render import renderer_fingerprint  # imported when measuring, as render is
    from reconstruction.fingerprint import networks_fingerprint

    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    names = list(profile.reconstruction_scenes)
    settings = row_settings(config, profile, recon)
    models: list[Reconstruction] = []
    rows = []
    bar = tqdm(names, unit="scene", desc=f"{kind} ({profile_name})", disable=not progress)
    renderer = renderer_fingerprint()
    weights = networks_fingerprint(recon) if networks else None

    def row_key(name: str) -> str:
        return content_key(f"{kind}-row", version, renderer, name, TIMING_REPEATS, settings, weights)

    for name in bar:
        path = out_dir / "rows" / kind / f"{name}.json"
        key = row_key(name)
        if not fresh and path.exists():
            saved = json.loads(path.read_text())
            if saved.get("key") == key:
                bar.write(f"{kind} {name}: reusing the row measured {saved['measured_at']} (pass fresh=True to measure again)")
                rows.append(saved["row"])
                continue
        if not models:
            bar.set_postfix_str("reconstruction networks" if networks else "")
            models.append(Reconstruction.load(names, recon, names, progress, blend_spp=blend_spp,
                                              variant_scenes=variant_scenes) if networks else None)
            # loading may have trained the networks into the store, which changes their weights' digest
            weights = networks_fingerprint(recon) if networks else None
        load_before = os.getloadavg()[0]
        with freed_memory_retained():  # a scene's renders and reconstructions, timed, reuse freed memory
            row = measure_scene(name, config, profile_name, models[0], bar)
        row["load_average"] = [load_before, os.getloadavg()[0]]
        record = {"key": row_key(name), "measured_at": time.strftime("%Y-%m-%d %H:%M:%S"), "row": row}
        atomic_write_bytes(path, json.dumps(record, indent=1).encode())
        rows.append(row)
    return rows


def generate(config: Config, profile_name: str, out_dir: str | Path, fresh: bool = False,
             progress: bool = True, denoisers: Sequence[str] = ()) -> list[Metric]:
    """Measure (or reuse) the run-time-against-error sweep and write its report.

    Parameters
    ----------
    config : Config
        Resolved configuration.
    profile_name : str
        Report profile (its ``reconstruction_scenes`` and ``sweep_*`` fields).
    out_dir : str or Path
        Writes ``error_time.md``, ``error_time.csv``, ``error_time/SCENE.png``,
        ``error_time.provenance.json`` and ``metrics/error_time.json``; rows in
        ``rows/error_time/``.
    fresh : bool
        Measure every scene again instead of reusing cached rows.
    progress : bool
        tqdm progress bars.
    denoisers : sequence of str
        Plug-in denoiser specs (``kdtrace report --denoiser``): the method ``kdtrace+SPEC``
        (:func:`measure_plugin_scene`) in the tables, the plots and the headline, cached
        apart from our rows (whose keys do not depend on them).

    Returns
    -------
    list of Metric
        Per scene: ``error_time/SCENE/kdtrace_over_mitsuba_paths_per_second`` (ratio, our
        path tracer over Mitsuba at the largest sweep spp, same run) and
        ``error_time/SCENE/denoiser_psnr_Nspp`` (psnr, ours + denoiser at the denoiser's
        training spp, fixed seeds); per plug-in ``error_time/SCENE/plugin:SPEC/failed``
        (zero) and ``.../psnr_Nspp`` (psnr).
    """
    out_dir = Path(out_dir)
    rows = scene_rows("error_time", ROW_VERSION, measure_scene, config, profile_name, out_dir, fresh, progress,
                      blend_spp=config.profile(profile_name).sweep_spp,
                      variant_scenes=sweep_variants(config.profile(profile_name)))
    if denoisers:
        extra = plugin_scene_rows(list(denoisers), config, profile_name, out_dir, fresh, progress)
        for row in extra:
            if row.get("failed"):
                warnings.warn(f"error_time: plug-in {row['plugin']!r} on {row['scene']}: {row['failed']}", ReportNote,
                              stacklevel=2)
        rows = with_plugins(rows, extra)
    write_outputs(rows, config, profile_name, out_dir)
    profile = config.profile(profile_name)
    recon = config.reconstruction.profile(profile.reconstruction_profile)
    metrics = [metric for row in rows for metric in scene_metrics(row, profile, recon)]
    write_metrics(out_dir, "error_time", metrics)
    return metrics


# ------------------------------------------------------------------ gated metrics


def scene_metrics(row: dict, profile: ProfileConfig, recon: ReconstructionProfile) -> list[Metric]:
    """The gated metrics of one scene's row (see :func:`generate`)."""
    points = pd.DataFrame(row["points"])
    name, spp = row["scene"], max(profile.sweep_spp)
    rate = {method: float(points[(points["method"] == method) & (points["spp"] == spp)]["seconds"].iloc[0])
            for method in ("kdtrace", "mitsuba")}
    metrics = [Metric(f"error_time/{name}/kdtrace_over_mitsuba_paths_per_second", "ratio", rate["mitsuba"] / rate["kdtrace"],
                      f"paths/s of our path tracer over Mitsuba path ({row['mitsuba_variant']}), {row['width']}x"
                      f"{row['height']} {spp} spp, same run")]
    for method, metric, what in (("kdtrace+denoiser", "denoiser", "per-scene denoiser"),
                                 *((f"kdtrace+{key}", f"{key}_denoiser", f"{key} per-scene denoiser")
                                   for key in SWEEP_VARIANTS)):
        denoised = points[(points["method"] == method) & (points["spp"] == recon.spp)]
        if len(denoised):
            metrics.append(Metric(f"error_time/{name}/{metric}_psnr_{recon.spp}spp", "psnr", float(denoised["psnr"].iloc[0]),
                                  f"dB, ours + {what} at {recon.spp} spp vs Mitsuba {row['reference']['spp']} spp"))
            if all_measured(denoised, "display_psnr", method):
                metrics.append(Metric(f"error_time/{name}/{metric}_display_psnr_{recon.spp}spp", "psnr",
                                      float(denoised["display_psnr"].iloc[0]),
                                      f"display-referred dB, ours + {what} at {recon.spp} spp"))
    blended = points[points["method"] == "kdtrace+denoiser-blend"]
    for error, prefix, space in (("psnr", "", "linear"), ("display_psnr", "display_", "display-referred")):
        if len(blended) and all_measured(blended, f"input_{error}", "kdtrace+denoiser-blend"):
            margins = blended[error] - blended[f"input_{error}"]
            worst = int(blended["spp"].iloc[int(np.argmin(margins.to_numpy()))])
            metrics.append(Metric(f"error_time/{name}/blended_denoiser_{prefix}margin_over_input_db", "psnr",
                                  float(margins.min()),
                                  f"dB ({space}), the smallest PSNR gain over its own noisy input of ours + denoiser "
                                  f"blended with the input, over the sweep spp (at {worst} spp); >= 0: never below the input"))
    if len(blended) and all_measured(blended, "input_flip", "kdtrace+denoiser-blend"):
        excess = blended["flip"] - blended["input_flip"]
        worst = int(blended["spp"].iloc[int(np.argmax(excess.to_numpy()))])
        metrics.append(Metric(f"error_time/{name}/blended_denoiser_flip_excess_over_input", "flip", float(excess.max()),
                              f"the largest FLIP of ours + denoiser blended with the input minus its noisy input's, "
                              f"over the sweep spp (at {worst} spp); <= 0: never worse than the input"))
    return metrics + plugin_metrics(row, recon)


def plugin_metrics(row: dict, recon: ReconstructionProfile) -> list[Metric]:
    """A scene's plug-in denoiser metrics: ``error_time/SCENE/plugin:SPEC/failed`` (zero), ``.../psnr_Nspp`` (psnr)."""
    from reports.plugins import metric_name

    points = pd.DataFrame(row["points"])
    metrics = []
    for spec, status in row.get("plugins", {}).items():
        failed = status != "ok"
        metrics.append(Metric(metric_name("error_time", row["scene"], spec, "failed"), "zero", int(failed),
                              status if failed else "ran"))
        at = points[(points["method"] == plugin_method(spec)) & (points["spp"] == recon.spp)]
        if len(at) and math.isfinite(float(at["psnr"].iloc[0])):
            metrics.append(Metric(metric_name("error_time", row["scene"], spec, f"psnr_{recon.spp}spp"), "psnr",
                                  float(at["psnr"].iloc[0]),
                                  f"dB, ours + plug-in at {recon.spp} spp vs Mitsuba {row['reference']['spp']} spp"))
    return metrics


def run_cli(generate_report: Callable[..., list[Metric]], description: str, argv: Sequence[str] | None) -> int:
    """Command line of a report generator: ``--profile`` (quick), ``--out`` (results/PROFILE), ``--config``, ``--fresh``."""
    from kdtrace.config import load_config

    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--profile", default="quick")
    parser.add_argument("--out", help="output folder (default results/PROFILE)")
    parser.add_argument("--config", help="TOML file overriding kdtrace/defaults.toml")
    parser.add_argument("--fresh", action="store_true", help="measure every scene again")
    args = parser.parse_args(argv)
    from kdtrace.cli import results_dir

    out = results_dir(args.profile, args.out)
    for metric in generate_report(load_config(args.config), args.profile, out, fresh=args.fresh):
        print(f"{metric.name} = {metric.value:.4g} ({metric.kind})")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m reports.error_time [--profile quick] [--out DIR] [--fresh] [--config FILE]``."""
    return run_cli(generate, __doc__.splitlines()[0], argv)


if __name__ == "__main__":
    raise SystemExit(main())
