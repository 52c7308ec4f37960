"""How the KD-tree build scales: build seconds against triangle count, with the fitted slope.

The paper cites O(N log^2 N) for its SAH build; Wald & Havran (2006) give O(N log N) for
a build that sorts once and inherits sorted order (ours for bounding-box splits,
:func:`kdtrace._kdtree_build.build_presorted`). Measured on nested random subsets of one
scene's triangles (a fixed-seed permutation; the first ``N`` of it for each size), so
the sizes differ in count and not in kind. Each size is built :data:`REPEATS` times on
one core after compilation (medians), for both variants (local = naive + pull-up).

The slope of log(seconds) against log(N) is fitted by least squares and stated beside
the slopes that ``N log N`` and ``N log^2 N`` themselves have over the same sizes (both
above 1 at these sizes), so the reader can see which the measurement follows.

Written to ``table1_build.md``, ``table1_build.csv`` and ``figures/build_scaling.png``;
cached in ``rows/build_scaling.json`` under a key of the build configuration and sizes.
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from tabulate import tabulate

from kdtrace import _kdtree_build
from kdtrace.cache import atomic_write_bytes, content_key, source_fingerprint
from kdtrace.config import Config
from kdtrace.kdtree import VARIANTS, build_kdtree
from kdtrace.provenance import machine
from kdtrace.scene import Scene
from kdtrace.scenes import load_scene
from references.ztest import loglog_slope
from reports.metrics import Metric

#: Fractions of the scene's triangles built (nested subsets), smallest first.
FRACTIONS = (1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0)
#: Builds per size and variant (medians).
REPEATS = 3
#: Seed of the triangle permutation.
SUBSET_SEED = 20261202
#: Version of the cached record's layout.
RECORD_VERSION = 1


def triangle_subset(scene: Scene, count: int, seed: int = SUBSET_SEED) -> Scene:
    """The first ``count`` triangles of a fixed random permutation of ``scene``'s, as a scene."""
    if not 1 <= count <= len(scene.triangles):
        raise ValueError(f"subset of {count} triangles out of range 1..{len(scene.triangles)}")
    order = np.random.default_rng(seed).permutation(len(scene.triangles))[:count]
    return Scene(f"{scene.name}-subset{count}", scene.vertices, scene.triangles[np.sort(order)],
                 scene.material_ids[np.sort(order)], scene.materials)


def fraction_counts(scene: Scene, fractions=FRACTIONS) -> list[int]:
    """Triangle counts of ``scene`` at each fraction of its triangles (at least 1)."""
    return [max(1, round(fraction * len(scene.triangles))) for fraction in fractions]


def measure(scene: Scene, config: Config, counts: list[int], repeats: int = REPEATS,
            once_above_seconds: float = float("inf")) -> dict:
    """Build seconds (medians of ``repeats``) of both variants at each subset size, and the fitted slopes.

    Parameters
    ----------
    scene : Scene
        The scene whose nested random subsets are built.
    config : Config
        Its ``kdtree`` section is the build recipe.
    counts : list of int
        Triangle counts, ascending, each at most the scene's.
    repeats : int
        Builds per size and variant (the median is kept).
    once_above_seconds : float
        A size whose first build of a variant takes longer than this is built once (its
        seconds barely move between builds, and at 10 million triangles each takes minutes).
    """
    rows = []
    for count in counts:
        subset = triangle_subset(scene, count)
        row = {"triangles": len(subset.triangles)}
        for variant in VARIANTS:
            times = []
            while len(times) < repeats and not (times and times[0] > once_above_seconds):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # zero-area triangles: counted in Table 1 already
                    tree = build_kdtree(subset, variant, config.kdtree, cache=False)
                times.append(tree.stats["build_seconds"])
            row[f"{variant}_seconds"] = float(np.median(times))
            row[f"{variant}_builds"] = len(times)
            row[f"{variant}_nodes"] = int(tree.stats["nodes"])
            row[f"{variant}_references"] = int(tree.stats["triangle_references"])
        rows.append(row)
    counts = [row["triangles"] for row in rows]
    n = np.asarray(counts, float)
    return {
        "scene": scene.name, "rows": rows, "repeats": repeats,
        "slopes": {variant: loglog_slope(counts, [row[f"{variant}_seconds"] for row in rows]) for variant in VARIANTS},
        # Sparser subsets make smaller trees per triangle: the slope against the naive tree's
        # references (the work the build writes) separates the algorithm from the tree's growth.
        "slopes_by_references": {variant: loglog_slope([row["naive_references"] for row in rows],
                                                       [row[f"{variant}_seconds"] for row in rows])
                                 for variant in VARIANTS},
        "reference_slopes": {"N log N": loglog_slope(n, n * np.log(n)), "N log^2 N": loglog_slope(n, n * np.log(n) ** 2)},
    }


def _key(scene_name: str, config: Config, fractions, repeats: int) -> str:
    return content_key("build-scaling", RECORD_VERSION, source_fingerprint(_kdtree_build), scene_name,
                       config.kdtree.__dict__, list(fractions), repeats,
                       SUBSET_SEED)


def generate(config: Config, scene_name: str, out_dir: Path, fresh: bool = False) -> tuple[dict, bool]:
    """Measure (or reuse) the scaling record of ``scene_name`` and write its table and figure.

    Returns
    -------
    record : dict
        :func:`measure`'s record with ``key``, ``measured_at`` and ``machine``.
    reused : bool
        True when the record came from ``rows/build_scaling.json``.
    """
    out_dir = Path(out_dir)
    path = out_dir / "rows" / "build_scaling.json"
    key = _key(scene_name, config, FRACTIONS, REPEATS)
    record = json.loads(path.read_text()) if path.exists() and not fresh else None
    reused = record is not None and record.get("key") == key
    if not reused:
        scene = load_scene(scene_name)
        record = {"key": key, "measured_at": time.strftime("%Y-%m-%d %H:%M:%S"), "machine": machine(),
                  **measure(scene, config, fraction_counts(scene))}
        atomic_write_bytes(path, json.dumps(record, indent=1).encode())
    write_outputs(record, out_dir)
    return record, reused


def write_outputs(record: dict, out_dir: Path, stem: str = "table1_build", figure: str = "build_scaling") -> None:
    """``STEM.md`` / ``STEM.csv`` and ``figures/FIGURE.png``, atomically."""
    from reports.figures import _figure, write_figure

    table = pd.DataFrame(record["rows"])
    slopes, reference = record["slopes"], record["reference_slopes"]
    host = record["machine"]
    text = (f"# Table 1 — KD-tree build scaling ({record['scene']})\n\n"
            f"Build seconds on one core after compilation (median of {record.get('repeats', REPEATS)}; "
            f"the builds column counts them) for nested random subsets of "
            f"{record['scene']}'s triangles; local = the naive build plus the pull-up. Machine: {host['cpu']}, "
            f"measured {record['measured_at']}. Fitted slope of log(seconds) against log(N): naive "
            f"{slopes['naive']:.2f}, local {slopes['local']:.2f}; over the same sizes N log N has slope "
            f"{reference['N log N']:.2f} and N log^2 N {reference['N log^2 N']:.2f}. Against the naive tree's "
            f"triangle references instead (smaller subsets are sparser and make fewer references per triangle): "
            f"naive {record['slopes_by_references']['naive']:.2f}, local {record['slopes_by_references']['local']:.2f}."
            "\n\n"
            + tabulate(table.to_dict("records"), headers="keys", tablefmt="github", floatfmt=".3f")
            + f"\n\n![build seconds against triangles](figures/{figure}.png)\n")
    atomic_write_bytes(out_dir / f"{stem}.md", text.encode())
    atomic_write_bytes(out_dir / f"{stem}.csv", table.to_csv(index=False).encode())
    drawing = _figure(5.0, 3.6)
    axes = drawing.add_subplot()
    for variant, marker in zip(VARIANTS, ("o", "s"), strict=True):
        axes.loglog(table["triangles"], table[f"{variant}_seconds"], marker=marker,
                    label=f"{variant} (slope {slopes[variant]:.2f})")
    n = table["triangles"].to_numpy(float)
    anchor = table["local_seconds"].iloc[-1] / (n[-1] * np.log(n[-1]))
    axes.loglog(n, anchor * n * np.log(n), "k:", label=f"N log N (slope {reference['N log N']:.2f})")
    axes.set_xlabel("triangles")
    axes.set_ylabel("build seconds (one core)")
    axes.set_title(f"KD-tree build\n{record['scene']}", fontsize="medium")
    axes.legend(fontsize="small")
    write_figure(drawing, out_dir / "figures" / f"{figure}.png")


def metrics_of(record: dict) -> list[Metric]:
    """The fitted slopes (``ratio``: a machine's constant factor cancels in a slope)."""
    return [Metric(f"table1/build_scaling/{variant}_slope", "ratio", record["slopes"][variant],
                   f"log-log slope of build seconds against triangles, {record['scene']}") for variant in VARIANTS]
