"""Measuring code of the reconstruction benchmarks (groups ``denoise`` and ``superres``).

* ``denoise``: our denoiser (HDR encode, network in the fast-inference mode chosen by
  :func:`reconstruction.speed.choose_options`, decode) against Intel Open Image Denoise
  on the same 512x512 buffers (a 4 spp render of our path tracer: colour, albedo; OIDN
  also gets the normal).
* ``superres``: our 2x superresolution 512 -> 1024 against bicubic upsampling of the
  same image (the Mitsuba reference of the frame, clipped to [0, 1]).

Every timing goes through ``benchmark.pedantic`` (:func:`bench._measure.timed_call`:
shortest of :data:`ROUNDS` rounds after :data:`WARMUP_ROUNDS`) and is validated
afterwards, raising :class:`~bench._measure.BenchmarkValidationError`:

* ours must give the same quality as the plain float32 model (PSNR against the
  reference within :data:`reconstruction.inference.MAX_PSNR_CHANGE` dB), finite, right shape;
* OIDN must beat its noisy input's PSNR;
* both upsamplers must reproduce their input when their output is reduced 2x again
  (at least :data:`MIN_CONSISTENCY_PSNR` dB).

``extra_info`` holds the PSNR of each result against the reference (superres: also
against the held-out 512x512 reference, upsampled from 256x256), and at the end of the
session the same-run ratio (OIDN/ours, bicubic/ours seconds).

A plug-in denoiser (``--bench-denoiser SPEC``, method ``plugin:SPEC``) is timed on the
same buffers as OIDN (colour, albedo, normal); its output is validated by
:class:`kdtrace.plugins.CheckedDenoiser` (a bad one raises ``PluginError``), it must leave
the shared buffers unchanged, its PSNR is recorded but not gated, and its rows get
``oidn_over_plugin_seconds``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import torch

from bench._measure import SEED, BenchmarkValidationError, check_unchanged, machine_info, timed_call, write_json_atomic
from bench._plugins import is_plugin, plugin_name
from kdtrace.plugins import CheckedDenoiser
from reconstruction import metrics, speed
from reconstruction.inference import MAX_PSNR_CHANGE, denoise, make_runner
from reconstruction.models import superresolve

#: Scene, frame side (pixels), samples per pixel of the noisy frame and of its Mitsuba reference.
SCENE, SIZE, SPP, REFERENCE_SPP = "cbox-original", 512, 4, 256
ROUNDS, WARMUP_ROUNDS = 5, 1
DENOISERS = ("oidn", "ours")
UPSAMPLERS = ("bicubic", "ours")
#: An upsampler's output reduced 2x (area) must match its input at least this well (dB).
MIN_CONSISTENCY_PSNR = 30.0


@dataclass
class ReconstructionBench:
    """The frame and trained nets the benchmarks share (built lazily, once per session).

    Attributes
    ----------
    scene : str
    size, spp, reference_spp : int
        Frame side (pixels) and samples per pixel of the noisy render and of the reference.
    profile : str
        Reconstruction profile the nets are trained (or reused) with.
    seed : int
    frame, denoiser, superres : optional
        Given directly (tests), else rendered / trained on first use.
    """

    scene: str = SCENE
    size: int = SIZE
    spp: int = SPP
    reference_spp: int = REFERENCE_SPP
    profile: str = "quick"
    seed: int = SEED
    frame: speed.Frame | None = None
    denoiser: torch.nn.Module | None = None
    superres: torch.nn.Module | None = None

    def __post_init__(self) -> None:
        from kdtrace.config import DEFAULT_CONFIG

        recon = DEFAULT_CONFIG.reconstruction.profile(self.profile)
        if self.frame is None:
            self.frame = speed.render_frame(self.scene, self.size, self.size, self.spp, recon.max_depth,
                                            self.seed % 2**31, self.reference_spp)
        if self.denoiser is None:
            from reconstruction.train import train_denoiser

            self.denoiser = train_denoiser([self.scene], recon, progress=False).model
        if self.superres is None:
            from reconstruction.train import train_superres

            self.superres = train_superres(recon, [self.scene], progress=False).model

    @cached_property
    def options(self) -> dict[str, str]:
        """Chosen execution mode per task (``"denoise"``, ``"superres"``), decided untimed."""
        decisions = speed.choose_options(self.denoiser, self.superres, self.frame)
        return {task: decision.chosen for task, decision in decisions.items()}

    @cached_property
    def low_res(self) -> np.ndarray:
        """The image upsampled by the ``superres`` benchmarks: the clipped reference, (S, S, 3)."""
        return np.clip(self.frame.reference, 0.0, 1.0)


def _check_image(image: np.ndarray, shape: tuple[int, ...], label: str) -> None:
    image = np.asarray(image)
    if image.shape != shape:
        raise BenchmarkValidationError(f"{label}: shape {image.shape}, expected {shape}")
    if not np.all(np.isfinite(image)):
        raise BenchmarkValidationError(f"{label}: {int(np.count_nonzero(~np.isfinite(image)))} NaN/inf values")


def measure_denoise(benchmark, bench: ReconstructionBench, method: str) -> dict[str, Any]:
    """Time one denoiser (``"ours"`` or ``"oidn"``) on the bench frame, then validate it."""
    frame = bench.frame
    info: dict[str, Any] = {"group": "denoise", "scene": bench.scene, "method": method, "width": frame.color.shape[1],
                            "height": frame.color.shape[0], "spp": frame.spp, "threads": torch.get_num_threads(),
                            "noisy_psnr": metrics.psnr(frame.color, frame.reference)}
    label = f"{bench.scene} denoise {method}"
    if method == "ours":
        option = bench.options["denoise"]
        runner = make_runner(bench.denoiser, option)
        result, seconds = timed_call(benchmark, lambda: denoise(bench.denoiser, frame.color, frame.albedo,
                                                                 runner=runner), ROUNDS, WARMUP_ROUNDS)
        _check_image(result, frame.color.shape, label)
        plain = metrics.psnr(denoise(bench.denoiser, frame.color, frame.albedo), frame.reference)
        info |= {"option": option, "fp32_psnr": plain}
    elif method == "oidn":
        from reconstruction.baselines import oidn

        result, seconds = timed_call(benchmark, lambda: oidn(frame.color, frame.albedo, frame.normal),
                                     ROUNDS, WARMUP_ROUNDS)
        _check_image(result, frame.color.shape, label)
    else:
        raise ValueError(f"unknown denoiser {method!r}; choose one of {DENOISERS}")
    info |= {"seconds": seconds, "psnr": metrics.psnr(result, frame.reference)}
    if method == "ours" and abs(info["psnr"] - info["fp32_psnr"]) > MAX_PSNR_CHANGE:
        raise BenchmarkValidationError(f"{label}: mode {info['option']} gives {info['psnr']:.3f} dB, float32 "
                                       f"{info['fp32_psnr']:.3f} dB (more than {MAX_PSNR_CHANGE} dB apart)")
    if method == "oidn" and not info["psnr"] > info["noisy_psnr"]:
        raise BenchmarkValidationError(f"{label}: {info['psnr']:.3f} dB, not above the noisy input's "
                                       f"{info['noisy_psnr']:.3f} dB")
    return info


def measure_plugin_denoise(benchmark, bench: ReconstructionBench, denoiser: CheckedDenoiser) -> dict[str, Any]:
    """Time a plug-in denoiser on the bench frame (OIDN's inputs: colour, albedo, normal).

    Returns the row of :func:`measure_denoise` with method ``plugin:SPEC``; raises
    :class:`kdtrace.plugins.PluginError` when the plug-in raises or returns an invalid image.
    """
    frame = bench.frame
    method = plugin_name(denoiser.spec)
    info: dict[str, Any] = {"group": "denoise", "scene": bench.scene, "method": method, "width": frame.color.shape[1],
                            "height": frame.color.shape[0], "spp": frame.spp, "threads": torch.get_num_threads(),
                            "noisy_psnr": metrics.psnr(frame.color, frame.reference)}
    inputs = {"color": frame.color, "albedo": frame.albedo, "normal": frame.normal}
    before = {name: image.copy() for name, image in inputs.items()}
    result, seconds = timed_call(benchmark, lambda: denoiser(frame.color, frame.albedo, frame.normal), ROUNDS, WARMUP_ROUNDS)
    check_unchanged(f"plug-in {denoiser.spec!r}", ((name, before[name], image) for name, image in inputs.items()))
    _check_image(result, frame.color.shape, f"{bench.scene} denoise {method}")
    return info | {"seconds": seconds, "psnr": metrics.psnr(result, frame.reference)}


def measure_superres(benchmark, bench: ReconstructionBench, method: str) -> dict[str, Any]:
    """Time one 2x upsampler (``"ours"`` or ``"bicubic"``) on the bench image, then validate it."""
    from reconstruction.baselines import bicubic
    from reconstruction.evaluate import downsample_2x

    image = bench.low_res
    shape = (2 * image.shape[0], 2 * image.shape[1], 3)
    label = f"{bench.scene} superres {method}"
    info: dict[str, Any] = {"group": "superres", "scene": bench.scene, "method": method, "input": list(image.shape[:2]),
                            "output": list(shape[:2]), "threads": torch.get_num_threads()}
    if method == "ours":
        option = bench.options["superres"]
        runner = make_runner(bench.superres, option)

        def upsample(low):
            return superresolve(bench.superres, low, runner=runner)

        info["option"] = option
    elif method == "bicubic":
        upsample = bicubic
    else:
        raise ValueError(f"unknown upsampler {method!r}; choose one of {UPSAMPLERS}")
    result, seconds = timed_call(benchmark, lambda: upsample(image), ROUNDS, WARMUP_ROUNDS)
    _check_image(result, shape, label)
    # quality on a held-out target: the image itself, reduced 2x and upsampled back
    target = image[: image.shape[0] // 2 * 2, : image.shape[1] // 2 * 2]
    low = np.clip(downsample_2x(target), 0.0, 1.0)
    info |= {"seconds": seconds, "consistency_psnr": metrics.psnr(downsample_2x(result), image),
             "psnr": metrics.psnr(upsample(low), target)}
    if method == "ours":
        info["fp32_psnr"] = metrics.psnr(superresolve(bench.superres, low), target)
        if abs(info["psnr"] - info["fp32_psnr"]) > MAX_PSNR_CHANGE:
            raise BenchmarkValidationError(f"{label}: mode {option} gives {info['psnr']:.3f} dB, float32 "
                                           f"{info['fp32_psnr']:.3f} dB (more than {MAX_PSNR_CHANGE} dB apart)")
    if info["consistency_psnr"] < MIN_CONSISTENCY_PSNR:
        raise BenchmarkValidationError(f"{label}: the output reduced 2x matches the input at only "
                                       f"{info['consistency_psnr']:.2f} dB (< {MIN_CONSISTENCY_PSNR})")
    return info


#: Per group: the baseline whose seconds divide by ours (higher ratio: ours faster).
BASELINES = {"denoise": "oidn", "superres": "bicubic"}


@dataclass
class ReconstructionResults:
    """Rows of one session and the extra_info dicts to complete with same-run ratios."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    extras: list[dict[str, Any]] = field(default_factory=list)

    def add(self, row: dict[str, Any], extra_info: dict[str, Any] | None = None) -> None:
        self.rows.append(row)
        self.extras.append(row if extra_info is None else extra_info)

    def ratios(self) -> dict[str, float]:
        """``GROUP`` -> baseline seconds / our seconds, for the groups where both ran."""
        seconds = {(row["group"], row["method"]): row["seconds"] for row in self.rows}
        return {group: seconds[group, baseline] / seconds[group, "ours"] for group, baseline in BASELINES.items()
                if (group, baseline) in seconds and (group, "ours") in seconds}

    def plugin_ratios(self) -> dict[str, dict[str, float]]:
        """``GROUP`` -> ``plugin:SPEC`` -> baseline seconds / the plug-in's seconds, where both ran."""
        seconds = {(row["group"], row["method"]): row["seconds"] for row in self.rows}
        ratios: dict[str, dict[str, float]] = {}
        for (group, method), plugin_seconds in seconds.items():
            baseline = BASELINES.get(group)
            if is_plugin(method) and (group, baseline) in seconds:
                ratios.setdefault(group, {})[method] = seconds[group, baseline] / plugin_seconds
        return ratios

    def finalize(self) -> None:
        """Write each group's ratio into every row and extra_info of that group, and the plug-ins' into theirs."""
        ratios, plugin_ratios = self.ratios(), self.plugin_ratios()
        for row, extra in zip(self.rows, self.extras, strict=True):
            if row["group"] in ratios:
                key = f"{BASELINES[row['group']]}_over_ours_seconds"
                row[key] = extra[key] = ratios[row["group"]]
            if row["method"] in plugin_ratios.get(row["group"], {}):
                key = f"{BASELINES[row['group']]}_over_plugin_seconds"
                row[key] = extra[key] = plugin_ratios[row["group"]][row["method"]]

    def table(self) -> str:
        """One line per timed method: seconds, PSNR and option."""
        width = max([8, *(len(row["method"]) for row in self.rows)])  # plug-ins' names are long
        lines = [f"{'group':9s} {'method':{width}s} {'seconds':>9s} {'PSNR dB':>8s}  option"]
        for row in self.rows:
            lines.append(f"{row['group']:9s} {row['method']:{width}s} {row['seconds']:9.4f} {row['psnr']:8.2f}  "
                         f"{row.get('option', '')}")
        lines += [f"{group}: {BASELINES[group]}/ours seconds = {ratio:.2f}" for group, ratio in self.ratios().items()]
        lines += [f"{group}: {BASELINES[group]}/{method} seconds = {ratio:.2f}"
                  for group, methods in self.plugin_ratios().items() for method, ratio in methods.items()]
        return "\n".join(lines)


def write_reconstruction_summary(path: Path, results: ReconstructionResults) -> None:
    """``path`` (JSON, atomic): rows, ratios (and the plug-ins', when any ran) and the machine."""
    plugin_ratios = results.plugin_ratios()
    write_json_atomic(path, {"rows": results.rows, "ratios": results.ratios(),
                             **({"plugin_ratios": plugin_ratios} if plugin_ratios else {}), "machine": machine_info()})
