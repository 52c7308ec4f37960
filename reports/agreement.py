"""The agreement report: our KD-trees against Embree, our path tracer against Mitsuba 3.

Per scene of the profile:

* **Embree** — the disagreements of both trees with Embree, summed over the five ray
  kinds, by class (ties, zero-area triangles, origins on a surface, tmax boundary,
  grazing rays, edges/vertices, unexplained). Taken from the Table 1 rows
  (:func:`reports.table1.load_rows`), so the table1 part must run first.
  Unexplained must be 0.
* **Mitsuba** — a per-pixel Welch/Z-test (:func:`references.ztest.compare_scene`) of a
  small frame of ours against a Mitsuba 3 reference, on the Cornell boxes of the profile
  (the scenes named ``cbox-*``; the larger scenes take minutes per reference and run in
  ``tests/test_agreement_mitsuba.py -m slow``). References are cached by content hash;
  settings are :data:`ZTEST_SPP`, :data:`ZTEST_REF_SPP`, :data:`ZTEST_SIZE` and
  :data:`ZTEST_MAX_DEPTH`, as in the test suite. A failing scene writes its images,
  error and p-value maps to ``ztest-failures/SCENE/``.

When Mitsuba's ``llvm_ad_rgb`` is unusable, references come from ``scalar_rgb``; the
report says so in a note (and the fallback warning reaches the report's index). When
Mitsuba is not installed the Z-test is skipped with a note, and its ``pass`` metrics are
absent, which the gate reports as missing.

Plug-in accelerators (``--accelerator SPEC``) get the same classes from their Table 1
rows (:func:`reports.table1.load_plugin_rows`) in a section of their own and
``agreement_plugins.csv``, with ``agreement/SCENE/plugin:SPEC/...`` metrics.

Writes ``agreement.md``, ``agreement.csv`` and ``metrics/agreement.json``: per scene
``agreement/SCENE/unexplained_embree`` (``zero``) and, for Z-tested scenes,
``agreement/SCENE/mitsuba_ztest`` (``pass``).
"""

from __future__ import annotations

import importlib.util
import warnings
from pathlib import Path

import pandas as pd
from tabulate import tabulate
from tqdm import tqdm

from kdtrace.cache import atomic_write_bytes
from kdtrace.config import Config
from references.agreement import EXPLANATIONS, OURS_EXACT, TIE, UNEXPLAINED, WRONG
from reports.metrics import Metric, write_metrics
from reports.notes import ReportNote
from reports.table1 import load_plugin_rows, load_rows

#: Z-test settings: our spp, Mitsuba's spp, square frame side, path length (Mitsuba's convention).
ZTEST_SPP, ZTEST_REF_SPP, ZTEST_SIZE, ZTEST_MAX_DEPTH = 256, 256, 32, 3
#: Scenes of a profile that get the Mitsuba Z-test: names starting with this prefix.
ZTEST_PREFIX = "cbox-"
#: Column order of the Embree classes (the data frame of references.agreement names ties "ties").
EMBREE_CLASSES = ("ties", *EXPLANATIONS, UNEXPLAINED, WRONG, OURS_EXACT)


def embree_by_class(rows: list[dict]) -> pd.DataFrame:
    """Per scene: rays compared and disagreements by class, summed over both trees and all ray kinds."""
    records = []
    for row in rows:
        counts = pd.DataFrame(row["agreement_counts"])
        records.append({"scene": row["scene"], "rays compared": int(counts["rays"].sum()),
                        "agree": int(counts["agree"].sum()),
                        **{(TIE if label == "ties" else label): int(counts[label].sum()) for label in EMBREE_CLASSES}})
    return pd.DataFrame(records)


def plugin_by_class(rows: list[dict]) -> list[dict]:
    """Per plug-in accelerator and scene: rays compared and disagreements by class (all ray kinds), or its failure.

    A failed plug-in's record has no counts, only its ``status`` (``failed: ...``).
    """
    records = []
    for row in rows:
        record = {"plug-in": row["plugin"], "scene": row["scene"], "status": row.get("failed") or "ok"}
        if not row.get("failed"):
            counts = pd.DataFrame(row["agreement_counts"])
            record.update({"rays compared": int(counts["rays"].sum()), "agree": int(counts["agree"].sum()),
                           **{(TIE if label == "ties" else label): int(counts[label].sum()) for label in EMBREE_CLASSES}})
        records.append(record)
    return records


def plugin_metrics(records: list[dict]) -> list[Metric]:
    """``agreement/SCENE/plugin:SPEC/{unexplained_embree,wrong_embree,failed}`` (``zero``), never in a baseline."""
    from reports.plugins import metric_name

    metrics = []
    for row in records:
        failed = row["status"] != "ok"
        metrics.append(Metric(metric_name("agreement", row["scene"], row["plug-in"], "failed"), "zero", int(failed),
                              row["status"] if failed else "ran"))
        if not failed:
            metrics += [Metric(metric_name("agreement", row["scene"], row["plug-in"], name), "zero", int(row[label]),
                               f"of {int(row['rays compared']):,} ray comparisons, 5 ray kinds")
                        for name, label in (("unexplained_embree", UNEXPLAINED), ("wrong_embree", WRONG))]
    return metrics


def ztest_scenes(scenes: tuple[str, ...]) -> list[str]:
    """The profile's scenes that get the Mitsuba Z-test (:data:`ZTEST_PREFIX`)."""
    return [name for name in scenes if name.startswith(ZTEST_PREFIX)]


def mitsuba_ztests(names: list[str], config: Config, seed: int, out_dir: Path, progress: bool) -> tuple[pd.DataFrame, list[str]]:
    """Z-test each named scene against Mitsuba 3; return one row per scene and the notes to show.

    Notes say which Mitsuba variant rendered the references (and why, when it fell back)
    or that Mitsuba is missing.
    """
    from references.llvm import LLVM_VARIANT, LLVMFallbackWarning

    if importlib.util.find_spec("mitsuba") is None:
        note = "Mitsuba 3 is not installed: the Z-test against Mitsuba was skipped (pip install mitsuba)."
        warnings.warn(note, ReportNote, stacklevel=2)
        return pd.DataFrame(), [note]
    from kdtrace.kdtree import build_kdtree
    from kdtrace.scenes import load_scene
    from references.ztest import compare_scene, write_failure_artefacts

    records, notes = [], []
    for name in tqdm(names, unit="scene", desc="Z-test against Mitsuba", disable=not progress):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            scene = load_scene(name)
            comparison = compare_scene(scene, ZTEST_SPP, ZTEST_REF_SPP, ZTEST_MAX_DEPTH, seed, ZTEST_SIZE, ZTEST_SIZE,
                                       tree=build_kdtree(scene, "local", config.kdtree))
        for warning in caught:
            if issubclass(warning.category, LLVMFallbackWarning) and str(warning.message) not in notes:
                notes.append(str(warning.message))
                warnings.warn(str(warning.message), LLVMFallbackWarning, stacklevel=2)
        summary = comparison.summary()
        if comparison.reference.variant != LLVM_VARIANT and not notes:
            notes.append(f"Mitsuba references rendered with {comparison.reference.variant}, not {LLVM_VARIANT}.")
        if not comparison.result.passed:
            write_failure_artefacts(out_dir / "ztest-failures" / name, comparison.ours.rgb, comparison.reference.rgb,
                                    comparison.result, extra=summary)
        records.append({"scene": name, "Z-test pass rate": summary["pass_rate"], "passed": summary["passed"],
                        "failed pixels": summary["failed_pixels"], "pixels": summary["pixels"],
                        "max |z|": summary["max_abs_z"], "relMSE": summary["relmse"],
                        "Mitsuba variant": summary["reference_variant"]})
    return pd.DataFrame(records), notes


def generate(config: Config, profile_name: str, out_dir: Path, fresh: bool = False, progress: bool = True,
             accelerators: list[str] | tuple[str, ...] = ()) -> list[Metric]:
    """Write the agreement report (agreement.md, agreement.csv, metrics/agreement.json).

    Parameters
    ----------
    config : Config
        Resolved configuration.
    profile_name : str
        Profile from ``[profiles.*]``; its scenes are the rows.
    out_dir : Path
        The report folder; must hold this configuration's Table 1 rows.
    fresh : bool
        Unused: the Embree half reuses Table 1's rows (``--fresh`` remeasures those) and
        Mitsuba references are cached by content (our renders are always redone).
    progress : bool
        Show progress bars.
    accelerators : sequence of str
        Plug-in accelerator specs: their disagreements by class from their Table 1 rows
        (:func:`reports.table1.load_plugin_rows`; a plug-in without one, or that failed
        there, is listed as ``failed: ...``), in a section of their own.

    Returns
    -------
    list of Metric
        ``agreement/SCENE/unexplained_embree`` (``zero``) for every scene and
        ``agreement/SCENE/mitsuba_ztest`` (``pass``) for every Z-tested scene; per plug-in
        and scene :func:`plugin_metrics`.
    """
    out_dir = Path(out_dir)
    profile = config.profile(profile_name)
    embree = embree_by_class(load_rows(config, profile_name, out_dir))
    mitsuba, notes = mitsuba_ztests(ztest_scenes(profile.scenes), config, profile.seed, out_dir, progress)

    metrics = [Metric(f"agreement/{row['scene']}/{name}", "zero", int(row[label]),
                      f"of {row['rays compared']:,} ray comparisons, both trees, 5 ray kinds")
               for row in embree.to_dict("records") for name, label in (("unexplained_embree", UNEXPLAINED),
                                                                         ("wrong_embree", WRONG))]
    metrics += [Metric(f"agreement/{row['scene']}/mitsuba_ztest", "pass", bool(row["passed"]),
                       f"per-pixel Welch/Z-test, {ZTEST_SIZE}x{ZTEST_SIZE}, {ZTEST_SPP}/{ZTEST_REF_SPP} spp")
                for row in mitsuba.to_dict("records")]

    text = [f"# Agreement ({profile_name} profile)\n",
            "## Embree: disagreements by class\n",
            f"Both KD-trees against Embree (robust mode), {profile.agreement_rays_per_kind:,} rays of each of 5 kinds "
            f"(camera, random, aimed at vertices, aimed at edge midpoints, shadow), seed {profile.seed}; from the "
            "Table 1 run. Every disagreement must fall into an explained class: unexplained must be 0. Per tree and "
            "ray kind: `kdtrace check-embree SCENE`.\n",
            tabulate(embree.to_dict("records"), headers="keys", tablefmt="github", intfmt=","), "",
            "## Mitsuba 3: per-pixel Z-test\n",
            f"Our path tracer ({ZTEST_SPP} spp) against a Mitsuba 3 reference ({ZTEST_REF_SPP} spp), "
            f"{ZTEST_SIZE}x{ZTEST_SIZE}, max_depth {ZTEST_MAX_DEPTH}, Welch's t per pixel and channel with Šidák "
            "correction (references/ztest.py); a scene passes when at least 99.75 % of its pixels pass.\n"]
    text += [f"> **Note:** {note}\n" for note in notes]
    if not mitsuba.empty:
        text.append(tabulate(mitsuba.to_dict("records"), headers="keys", tablefmt="github", floatfmt=".4g"))
    if accelerators:
        plugins = plugin_by_class(load_plugin_rows(config, profile_name, out_dir, list(accelerators)))
        metrics += plugin_metrics(plugins)
        for row in plugins:
            if row["status"] != "ok":
                warnings.warn(f"agreement: plug-in {row['plug-in']!r} on {row['scene']}: {row['status']}", ReportNote,
                              stacklevel=2)
        text += ["", "## Plug-in accelerators: disagreements with Embree by class\n",
                 "Each plug-in (`--accelerator SPEC`) against Embree on the same rays, classifier and float64 oracle as "
                 "our trees (from its Table 1 rows); `ours exact, Embree not` counts rays where the plug-in equals the "
                 "oracle and Embree does not. Unexplained and wrong must be 0. Per ray kind: "
                 "`kdtrace check-embree SCENE --accelerator SPEC`.\n",
                 tabulate(plugins, headers="keys", tablefmt="github", intfmt=",", missingval="")]
        atomic_write_bytes(out_dir / "agreement_plugins.csv", pd.DataFrame(plugins).to_csv(index=False).encode())
    atomic_write_bytes(out_dir / "agreement.md", ("\n".join(text) + "\n").encode())
    table = embree.merge(mitsuba, on="scene", how="left") if not mitsuba.empty else embree
    atomic_write_bytes(out_dir / "agreement.csv", table.to_csv(index=False).encode())
    write_metrics(out_dir, "agreement", metrics)
    return metrics
