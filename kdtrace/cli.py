"""The ``kdtrace`` command line.

Subcommands: ``scenes`` (list scene descriptions), ``build`` (build and cache the
KD-trees of a scene, print their statistics), ``check-embree`` (hit-for-hit agreement
with Embree), ``render`` (path trace to EXR and PNG), ``compare`` (every metric of two
images, linear and display-referred, and a FLIP map), ``report`` (the main job: every
report part of a profile), ``verdict`` (its one-page verdict, again from a results folder),
``gate`` and ``update-baseline`` (the CI regression gate).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
import warnings
from pathlib import Path

from tabulate import tabulate
from tqdm import tqdm

from kdtrace.cache import DiskFullError
from kdtrace.config import load_config

REPOSITORY = Path(__file__).resolve().parents[1]
#: Environment variable naming the folder of generated results (default ``results`` in the checkout).
RESULTS_ENV = "KDTRACE_RESULTS"


def results_dir(profile: str, out: str | None = None) -> Path:
    """Where a profile's run writes (``--out``, else ``$KDTRACE_RESULTS/PROFILE``, else ``results/PROFILE``)."""
    if out:
        return Path(out)
    return Path(os.environ.get(RESULTS_ENV) or REPOSITORY / "results") / profile


def _positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (exit 2 with the option named otherwise)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"must be a positive finite number, got {text!r}")
    return value


class _OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line on stderr (no usage block) and exit status 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message}\n")


class OptionError(ValueError):
    """A command-line value that is wrong in context (unknown name, conflicting options); its message starts with the option."""


def _integer(text: str, minimum: int, allowed: tuple[int, ...] = ()) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < minimum and value not in allowed:
        also = "".join(f" or {value_}" for value_ in allowed)
        raise argparse.ArgumentTypeError(f"must be an integer >= {minimum}{also}, got {text!r}")
    return value


def _positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    return _integer(text, 1)


def _non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0."""
    return _integer(text, 0)


def _max_depth(text: str) -> int:
    """argparse type: a path length >= 1 (Mitsuba's convention), or -1 for unbounded."""
    return _integer(text, 1, (-1,))


SCENE_SUFFIXES = (".toml", ".obj", ".ply")


def _scene(text: str) -> str:
    """argparse type: a scene name of ``scenes/`` or an existing .toml, .obj or .ply file."""
    from kdtrace.scenes import list_scenes

    if Path(text).suffix.lower() in SCENE_SUFFIXES:
        if Path(text).is_dir():
            raise argparse.ArgumentTypeError(f"{text} is a folder, not a scene file")
        if not Path(text).is_file():
            raise argparse.ArgumentTypeError(f"{text}: no such scene file")
        return text
    if text not in list_scenes():
        raise argparse.ArgumentTypeError(f"unknown scene {text!r}; available: {', '.join(list_scenes())} "
                                         f"(or a {', '.join(SCENE_SUFFIXES)} file)")
    return text


def _names(text: str) -> list[str]:
    """argparse type: a comma-separated list of one or more names, none empty."""
    names = [name.strip() for name in text.split(",")]
    if not any(names):
        raise argparse.ArgumentTypeError("empty list; give one or more comma-separated names")
    if not all(names):
        raise argparse.ArgumentTypeError(f"empty name in {text!r}")
    return names


def _spec(text: str) -> str:
    """argparse type: a non-empty plug-in spec (or comma-separated specs)."""
    if not text.strip(" ,"):
        raise argparse.ArgumentTypeError("empty plug-in name")
    return text


def _existing_file(text: str) -> Path:
    """argparse type: a file that exists."""
    if Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file")
    if not Path(text).is_file():
        raise argparse.ArgumentTypeError(f"{text}: no such file")
    return Path(text)


def _existing_folder(text: str) -> Path:
    """argparse type: a folder that exists."""
    if Path(text).exists() and not Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file, not a folder")
    if not Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"{text}: no such folder")
    return Path(text)


def _folder(text: str) -> Path:
    """argparse type: a folder to write into (created when missing), not an existing file."""
    if Path(text).exists() and not Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a file, not a folder")
    return Path(text)


def _file_to_write(text: str) -> Path:
    """argparse type: a file to write, not an existing folder."""
    if Path(text).is_dir():
        raise argparse.ArgumentTypeError(f"{text} is a folder, not a file")
    return Path(text)


def _check_specs(option: str, values: list[str] | None, group: str) -> None:
    """Resolve each plug-in spec of ``option`` (without calling it); OptionError naming it otherwise."""
    from kdtrace.plugins import PluginError, resolve_factory

    for value in values or ():
        for spec in (spec.strip() for spec in value.split(",")):
            if spec:
                try:
                    resolve_factory(spec, group)
                except PluginError as error:
                    raise OptionError(f"{option}: {error}") from None


def _check_options(args, config) -> None:
    """Checks that need the configuration or several options; OptionError naming the option."""
    from kdtrace.plugins import ACCELERATOR_GROUP, DENOISER_GROUP

    command = args.command
    if command in ("report", "gate", "update-baseline", "verdict", "production"):
        try:
            config.profile(args.profile)
        except ValueError as error:
            raise OptionError(f"--profile: {error}") from None
    if command == "quality":
        try:
            config.reconstruction.profile(args.profile)
        except ValueError as error:
            raise OptionError(f"--profile: {error}") from None
    if command == "dataset":
        try:
            config.reconstruction.profile(args.dataset_profile)
        except ValueError as error:
            raise OptionError(f"--profile: {error}") from None
        if args.in_process and (args.scheduler or args.workers is not None):
            raise OptionError("--in-process: renders without Dask; it cannot be combined with "
                              + " and ".join(option for option, value in (("--scheduler", args.scheduler),
                                                                           ("--workers", args.workers is not None))
                                             if value))
    if command == "quality":
        from kdtrace.scenes import list_scenes

        unknown = [name for name in args.scenes if name not in list_scenes()]
        if unknown:
            raise OptionError(f"--scenes: unknown scenes {unknown}; available: {', '.join(list_scenes())}")
    if command == "report":
        profile_scenes = config.profile(args.profile).scenes
        unknown = [name for name in args.scenes or () if name not in profile_scenes]
        if unknown:
            raise OptionError(f"--scenes: {unknown} not in profile {args.profile!r}; its scenes: {', '.join(profile_scenes)}")
        if args.parts:
            from reports.main import resolve_parts

            try:
                resolve_parts(args.parts)
            except ValueError as error:
                raise OptionError(f"--parts: {error}") from None
        _check_specs("--accelerator", args.accelerator, ACCELERATOR_GROUP)
        _check_specs("--denoiser", args.denoiser, DENOISER_GROUP)
    if command == "check-embree":
        _check_specs("--accelerator", args.accelerator, ACCELERATOR_GROUP)
    if command == "verdict" and args.results is not None and args.profile != "quick":
        raise OptionError("--profile: picks the results folder only without RESULTS_DIR; give one of the two")


def _writable(folder: Path) -> Path:
    """``folder``, created if needed; ValueError naming it when nothing can be written there."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".write-test-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        raise ValueError(f"results folder {folder} is not writable ({error.strerror or error})") from error
    return folder


def _scenes(args, config) -> int:
    from kdtrace.scenes import list_scenes, load_scene

    rows = []
    for name in tqdm(list_scenes(), unit="scene", desc="loading"):
        summary = load_scene(name).summary()
        rows.append(summary)
    print(tabulate(rows, headers="keys", tablefmt="github"))
    return 0


def _build(args, config) -> int:
    from kdtrace.kdtree import VARIANTS, build_kdtree
    from kdtrace.scenes import load_scene

    scene = load_scene(args.scene)
    variants = VARIANTS if args.variant == "both" else (args.variant,)
    rows = []
    with tqdm(variants, unit="tree", desc=f"building {scene.name}") as bar:
        for variant in bar:
            bar.set_postfix_str(variant)
            rows.append(build_kdtree(scene, variant, config.kdtree, cache=not args.no_cache).stats)
    print(tabulate(rows, headers="keys", tablefmt="github"))
    return 0


def _check_embree(args, config) -> int:
    from kdtrace.plugins import OUR_ACCELERATORS
    from references.agreement import OURS_EXACT, UNEXPLAINED, WRONG, main_check_embree

    rays = args.rays or config.embree_check.rays_per_kind
    seed = config.embree_check.seed if args.seed is None else args.seed
    specs = tuple(spec for value in args.accelerator or OUR_ACCELERATORS for spec in value.split(",") if spec)
    df, text = main_check_embree(args.scene, rays, seed, specs)
    print(text)
    unexplained = int(df[UNEXPLAINED].sum())
    wrong = int(df[WRONG].sum())
    print(f"wrong (the float64 oracle finds a nearer hit): {wrong}")
    print(f"unexplained disagreements: {unexplained}")
    print(f"disagreements where ours is exact and Embree is not: {int(df[OURS_EXACT].sum())}")
    return 1 if unexplained or wrong else 0


def _render(args, config) -> int:
    from kdtrace.imageio import write_render
    from kdtrace.render import render
    from kdtrace.scenes import load_scene

    scene = load_scene(args.scene)
    with tqdm(total=1, unit="frame", desc=f"rendering {scene.name}") as bar:
        result = render(scene, spp=args.spp, max_depth=args.max_depth, seed=args.seed,
                        width=args.width, height=args.height, variant=args.variant)
        bar.update()
    paths = write_render(result, args.out, scene.name)
    stats = result.stats
    print(f"{scene.name}: {result.seconds:.2f} s, {stats.get('paths_per_second', 0):,.0f} paths/s; wrote "
          + ", ".join(str(p) for p in paths.values()))
    return 0


def _reference(args, config) -> int:
    from references.mitsuba import main_reference

    reference = main_reference(args.scene, args.spp, args.max_depth, args.seed, args.width, args.height,
                               force=args.force, output_dir=args.out)
    print(f"{args.scene}: {reference.spp} spp with Mitsuba {reference.variant} in {reference.seconds:.1f} s; images in {args.out}")
    return 0


def _compare_mitsuba(args, config) -> int:
    from references.ztest import main_compare

    summary = main_compare(args.scene, args.spp, args.ref_spp, args.max_depth, args.seed, args.width, args.height, args.out)
    print(tabulate([{k: v for k, v in summary.items() if not isinstance(v, (dict, list))}], headers="keys", tablefmt="github"))
    return 0 if summary.get("passed") else 1


def _quality(args, config) -> int:
    from reconstruction.evaluate import main_quality

    table = main_quality(args.scenes, args.profile, args.out, progress=True)
    print(tabulate(table, headers="keys", tablefmt="github", showindex=False))
    return 0


def _dataset(args, config) -> int:
    from kdtrace.distributed import (
        SchedulerUnreachableError,
        UnitError,
        VersionMismatchError,
    )
    from reconstruction.data import DatasetWriteError, generate_dataset

    profile = config.reconstruction.profile(args.dataset_profile)
    workers = config.distributed.workers if args.workers is None else args.workers
    where = {} if args.in_process else {"scheduler": args.scheduler, "workers": workers}  # workers: use Dask
    started = time.perf_counter()
    try:
        dataset = generate_dataset(args.scene, profile, progress=True, variant=args.mitsuba_variant,
                                   config=config.distributed, **where)
    except (SchedulerUnreachableError, VersionMismatchError, UnitError, DatasetWriteError) as error:
        print(f"kdtrace: error: {error}", file=sys.stderr)
        return 2
    views = dataset.manifest["views"]
    print(f"{dataset.manifest['scene']}: {sum(v['accepted'] for v in views)} of {len(views)} views accepted, "
          f"{sum(v.get('unit_seconds', 0.0) for v in views):.0f} s of rendering by "
          f"{len({v.get('worker') for v in views})} workers, {time.perf_counter() - started:.0f} s wall; {dataset.root}")
    return 0


def _compare(args, config) -> int:
    from kdtrace.imageio import read_image, write_colour_map
    from reconstruction import metrics

    test, test_ldr = read_image(args.test)
    reference, reference_ldr = read_image(args.reference)
    if test.shape != reference.shape:
        raise ValueError(f"{args.test} is {test.shape[1]}x{test.shape[0]}, {args.reference} is "
                         f"{reference.shape[1]}x{reference.shape[0]}: the images must have the same size")
    if test_ldr != reference_ldr:
        warnings.warn("one image is display-encoded (PNG/JPEG) and the other linear: the display-encoded one is "
                      "decoded with the sRGB curve, but whatever exposure made it is not undone", stacklevel=1)
    if args.exposure is not None:
        exposure, rule = args.exposure, "--exposure"
    elif reference_ldr:
        exposure, rule = 1.0, "1: the reference is a display-encoded image"
    else:
        exposure = metrics.auto_exposure(reference, str(args.reference))
        rule = f"the reference's {metrics.EXPOSURE_PERCENTILE:g}th-percentile luminance to 1"
    values = metrics.all_metrics(test, reference, exposure)
    rows = [("linear (clipped to [0, 1])", "PSNR (dB)", values["psnr"]), ("linear (clipped to [0, 1])", "RMSE", values["rmse"]),
            ("linear (clipped to [0, 1])", "SSIM", values.get("ssim")), ("HDR (unclipped)", "relMSE", values["relmse"]),
            ("HDR (unclipped)", "SMAPE", values["smape"]), ("display", "PSNR (dB)", values["display_psnr"]),
            ("display", "RMSE", values["display_rmse"]), ("display", "SSIM", values.get("display_ssim")),
            ("display", "FLIP (LDR, 67 ppd)", values["flip"])]
    print(f"{args.test} against {args.reference}, {test.shape[1]}x{test.shape[0]}"
          + (" (display-encoded test image, decoded to linear)" if test_ldr else ""))
    print(f"display tonemapping: exposure {exposure:.6g} ({rule}), clip to [0, 1], sRGB transfer curve\n")
    print(tabulate([(space, name, "-" if value is None else f"{value:.6g}") for space, name, value in rows],
                   headers=("space", "metric", "value"), tablefmt="github", disable_numparse=True))
    if args.map:
        error_map, _ = metrics.flip_map(test, reference, exposure)
        print(f"\nFLIP error map (magma, 0 black to 1 white): {write_colour_map(args.map, error_map)}")
    return 0


def _report(args, config) -> int:
    from reports.main import run_report

    scenes, parts = args.scenes, args.parts
    out_dir = _writable(results_dir(args.profile, args.out))  # before any work
    if args.scheduler:
        # the environment is where every part (and the dataset generator) looks for a scheduler
        from kdtrace.distributed import SCHEDULER_ENV

        os.environ[SCHEDULER_ENV] = args.scheduler
    started = time.perf_counter()
    from reports.plugins import parse_specs

    outcome = run_report(config, args.profile, out_dir, scenes=scenes, fresh=args.fresh, gate=args.gate, parts=parts,
                         accelerators=parse_specs(args.accelerator), denoisers=parse_specs(args.denoiser))
    print(f"\nwrote {out_dir}/README.md (index of every table and plot) and provenance.json; "
          f"{time.perf_counter() - started:.0f} s in all")
    for failure in outcome.correctness_failures:
        print(f"FAIL: {failure}")
    if outcome.gate_text:
        print("\n" + outcome.gate_text)
    return 0 if outcome.ok else 1


def _production(args, config) -> int:
    from reports.production import generate

    if args.triangles is not None:
        config = dataclasses.replace(config, production=dataclasses.replace(
            config.production, triangles=args.triangles,
            scaling_sizes=tuple(size for size in config.production.scaling_sizes if size < args.triangles)
            + (args.triangles,)))
    out_dir = _writable(results_dir(args.profile, args.out))
    started = time.perf_counter()
    generate(config, args.profile, out_dir, fresh=args.fresh)
    print(f"wrote {out_dir}/table1_production.md and table1_build_production.md; "
          f"{time.perf_counter() - started:.0f} s in all")
    return 0


def _verdict(args, config) -> int:
    from reports.verdict_page import link_from_index, write_verdict

    out_dir = Path(args.results) if args.results else results_dir(args.profile)
    written = write_verdict(out_dir, args.profile if not args.results else None)
    linked = link_from_index(out_dir)
    print(f"wrote {written['markdown']} and {written['html']} ({written['html'].stat().st_size / 1e6:.2f} MB)"
          + ("; linked first from README.md" if linked else "; no README.md index to link it from"))
    return 0


def _gate(args, config) -> int:
    from reports.gate import run_gate

    out_dir = results_dir(args.profile, args.out)
    passed, text = run_gate(out_dir, args.profile, config.gate, directory=args.baselines)
    print(text)
    return 0 if passed else 1


def _update_baseline(args, config) -> int:
    from reports.gate import update_baseline

    out_dir = results_dir(args.profile, args.out)
    paths, note = update_baseline(out_dir, args.profile, directory=args.baselines)
    print(f"{note}; review with `git diff {' '.join(map(str, paths))}`")
    return 0


def build_parser() -> argparse.ArgumentParser:
    defaults = load_config()
    parser = _OneLineParser(prog="kdtrace", description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=_existing_file, help="TOML file overriding kdtrace/defaults.toml")
    parser.add_argument("--quiet", action="store_true", help="do not print warnings")
    sub = parser.add_subparsers(dest="command", required=True)

    sub.add_parser("scenes", help="list the scene descriptions with their counts").set_defaults(run=_scenes)

    build = sub.add_parser("build", help="build (or load cached) KD-trees and print their statistics")
    build.add_argument("scene", type=_scene, help="scene name, .toml, .obj or .ply")
    build.add_argument("--variant", choices=("naive", "local", "both"), default="both")
    build.add_argument("--no-cache", action="store_true", help="rebuild even when a cached tree exists")
    build.set_defaults(run=_build)

    check = sub.add_parser("check-embree", help="compare our two trees (or --accelerator plug-ins) with Embree ray for ray")
    check.add_argument("scene", type=_scene, help="scene name, .toml, .obj or .ply")
    check.add_argument("--rays", type=_positive_int, help="rays per kind (default from the configuration: 1,000,000)")
    check.add_argument("--seed", type=_non_negative_int)
    check.add_argument("--accelerator", action="append", type=_spec, metavar="NAME",
                       help="plug-in to compare: a registered name (local, naive, embree, ...) or package.module:factory; "
                            "repeatable or comma-separated (default: our two trees, local and naive)")
    check.set_defaults(run=_check_embree)

    render = sub.add_parser("render", help="path trace a scene and write EXR (linear) and PNG (sRGB) images")
    render.add_argument("scene", type=_scene, help="scene name, .toml, .obj or .ply")
    render.add_argument("--spp", type=_positive_int, help=f"samples per pixel (default {defaults.render.spp})")
    render.add_argument("--max-depth", type=_max_depth, help="Mitsuba's convention: 2 direct light, 3 one bounce, -1 unbounded")
    render.add_argument("--seed", type=_non_negative_int)
    render.add_argument("--width", type=_positive_int, help="default: the scene camera's")
    render.add_argument("--height", type=_positive_int, help="default: the scene camera's")
    render.add_argument("--variant", choices=("local", "naive"), default="local")
    render.add_argument("--out", type=_folder, default="renders", help="output folder")
    render.set_defaults(run=_render)

    compare = sub.add_parser("compare", help="every metric of two images, linear and display-referred, and a FLIP map")
    compare.add_argument("test", type=_existing_file, help="image to judge: EXR or NPY (linear), PNG or JPEG (sRGB)")
    compare.add_argument("reference", type=_existing_file, help="the reference image, same size")
    compare.add_argument("--exposure", type=_positive_float,
                         help="display exposure (default: the reference's 99th-percentile luminance to 1; 1 for PNG)")
    compare.add_argument("--map", type=_file_to_write, metavar="PNG", help="also write the FLIP error map here")
    compare.set_defaults(run=_compare)

    reference = sub.add_parser("reference", help="render (or fetch from the cache) a Mitsuba 3 reference image")
    reference.add_argument("scene", type=_scene)
    reference.add_argument("--spp", type=_positive_int, default=256)
    reference.add_argument("--max-depth", type=_positive_int, default=defaults.render.max_depth)
    reference.add_argument("--seed", type=_non_negative_int, default=0)
    reference.add_argument("--width", type=_positive_int)
    reference.add_argument("--height", type=_positive_int)
    reference.add_argument("--force", action="store_true", help="render again even when cached")
    reference.add_argument("--out", type=_folder, default="out/references")
    reference.set_defaults(run=_reference)

    compare = sub.add_parser("compare-mitsuba", help="per-pixel Z-test of our render against Mitsuba 3's")
    compare.add_argument("scene", type=_scene)
    compare.add_argument("--spp", type=_positive_int, default=256, help="our samples per pixel")
    compare.add_argument("--ref-spp", type=_positive_int, default=256, help="Mitsuba's samples per pixel")
    compare.add_argument("--max-depth", type=_positive_int, default=defaults.render.max_depth)
    compare.add_argument("--seed", type=_non_negative_int, default=0)
    compare.add_argument("--width", type=_positive_int, default=32)
    compare.add_argument("--height", type=_positive_int, default=32)
    compare.add_argument("--out", type=_folder, default="out/compare", help="folder for images, error and p-value maps")
    compare.set_defaults(run=_compare_mitsuba)

    quality = sub.add_parser("quality", help="train (or reuse) the denoiser and superresolution nets; tabulate test quality")
    quality.add_argument("--scenes", type=_names, default="cbox-original", help="comma-separated scene names")
    quality.add_argument("--profile", default="quick", help="reconstruction profile (quick, paper)")
    quality.add_argument("--out", type=_folder, default="reports/quality", help="folder for quality.md and quality.csv")
    quality.set_defaults(run=_quality)

    dataset = sub.add_parser("dataset", help="generate (or complete) a Precision Graphics dataset, on Dask workers")
    dataset.add_argument("scene", type=_scene, help="scene name, .toml, .obj or .ply")
    dataset.add_argument("--profile", dest="dataset_profile", default="quick",
                         help="reconstruction profile (quick, paper)")
    dataset.add_argument("--scheduler", help="address of a running Dask scheduler (default $KDTRACE_SCHEDULER, "
                         "else a local cluster)")
    dataset.add_argument("--workers", type=_non_negative_int, help="worker processes of the local cluster (default: one per core)")
    dataset.add_argument("--mitsuba-variant", help="Mitsuba variant of the references, e.g. cuda_ad_rgb on GPU "
                         "workers (falls back when unusable)")
    dataset.add_argument("--in-process", action="store_true", help="render in this process, without Dask")
    dataset.set_defaults(run=_dataset)

    report = sub.add_parser("report", help="the main job: every report part of a profile, an index, optionally the gate")
    report.add_argument("--profile", default="quick", help="profile name from the configuration (quick, standard, paper)")
    report.add_argument("--scenes", type=_names, help="comma-separated subset of the profile's scenes")
    report.add_argument("--parts", type=_names, help="comma-separated report parts (default all: table1, agreement, "
                        "reconstruction, error_time, combined, scaleout)")
    report.add_argument("--out", type=_folder, help="output folder (default results/PROFILE; $KDTRACE_RESULTS/PROFILE when set)")
    report.add_argument("--fresh", action="store_true", help="measure everything again instead of reusing results")
    report.add_argument("--gate", action="store_true", help="then compare with the committed baselines; exit 1 on a regression")
    report.add_argument("--scheduler", help="address of a running Dask scheduler: Table 1 rows and dataset views "
                        "become units of work on its workers (default $KDTRACE_SCHEDULER, else all in this process)")
    report.add_argument("--accelerator", action="append", type=_spec, metavar="NAME",
                        help="also put this plug-in accelerator through Table 1 and the agreement part: a registered "
                             "name (kdtrace.accelerators) or package.module:factory; repeatable or comma-separated")
    report.add_argument("--denoiser", action="append", type=_spec, metavar="NAME",
                        help="also put this plug-in denoiser through Tables 2 and 6 and the error-time sweep: a "
                             "registered name (kdtrace.denoisers) or package.module:factory; repeatable or comma-separated")
    report.set_defaults(run=_report)

    production = sub.add_parser("production", help="Table 1 at production scale: a generated scene of 10 million "
                                "triangles ([production] in the configuration) against Embree")
    production.add_argument("--profile", default="standard", help="profile whose ray counts and frame size are used, "
                            "and whose results folder is written (default standard)")
    production.add_argument("--triangles", type=_positive_int, help="at least this many triangles (default "
                            f"{defaults.production.triangles:,}, [production] triangles)")
    production.add_argument("--out", type=_folder, help="output folder (default results/PROFILE)")
    production.add_argument("--fresh", action="store_true", help="measure every stage again instead of resuming")
    production.set_defaults(run=_production)

    verdict = sub.add_parser("verdict", help="write the one-page verdict (verdict.md, verdict.html) of a results folder "
                             "again, from what its report wrote; measures nothing")
    verdict.add_argument("results", nargs="?", type=_existing_folder, metavar="RESULTS_DIR",
                         help="results folder of a report run (default results/PROFILE)")
    verdict.add_argument("--profile", default="quick", help="profile whose results folder to use without RESULTS_DIR")
    verdict.set_defaults(run=_verdict)

    for command, run, what in (("gate", _gate, "compare the latest run's metrics with the committed baseline"),
                               ("update-baseline", _update_baseline, "rewrite the committed baseline from the latest run")):
        parser_ = sub.add_parser(command, help=what)
        parser_.add_argument("--profile", default="quick", help="profile name (selects results/PROFILE and the baselines)")
        parser_.add_argument("--out", type=_existing_folder, help="results folder of the run (default results/PROFILE)")
        parser_.add_argument("--baselines", type=_existing_folder if command == "gate" else _folder, metavar="DIR",
                             help="folder of the baselines PROFILE.json and PROFILE.ratios.KIND.json "
                                  "(default reports/baseline)")
        parser_.set_defaults(run=run)
    return parser


def _show_warnings_as_lines(quiet: bool) -> None:
    """Print each distinct warning once, as ``warning: MESSAGE`` on stderr; none when ``quiet``.

    Call inside :class:`warnings.catch_warnings`, which restores the filters and
    ``warnings.showwarning``. Scene warnings carry ``FILE:LINE:`` in their message, so
    a message repeated by a second load of the same file (or a cache hit) is shown once.
    """
    if quiet:
        warnings.simplefilter("ignore")
        return
    from kdtrace.io import SceneWarning

    warnings.simplefilter("always", SceneWarning)  # repeats are dropped below, by message
    shown: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = str(message) if issubclass(category, SceneWarning) else f"{category.__name__}: {message}"
        if text not in shown:
            shown.add(text)
            tqdm.write(f"warning: {text}", file=sys.stderr)  # above any progress bar

    warnings.showwarning = show


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (2: a bad argument or an unusable input, on one line)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exit_:  # --help (0) or a bad argument (2, its one line already printed)
        return exit_.code if isinstance(exit_.code, int) else 2
    with warnings.catch_warnings():
        _show_warnings_as_lines(args.quiet)
        try:
            config = load_config(args.config)
            _check_options(args, config)  # unknown names and conflicts fail before any work
            return args.run(args, config)
        except (ValueError, FileNotFoundError, DiskFullError) as error:
            print(f"kdtrace: error: {error}", file=sys.stderr)
            return 2


if __name__ == "__main__":
    sys.exit(main())
