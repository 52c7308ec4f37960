"""The verdict of a report run, judged: what the verdict page (:mod:`reports.verdict_page`) says.

Reads what the report parts wrote into a results folder and measures nothing:

* :func:`judge`: each of the paper's claims (:data:`CLAIMS`) with the paper's figure, ours
  and a verdict, from the run's CSV tables (:class:`RunTables`) and
  :mod:`reports.paper_figures`; a claim measured in both image spaces (linear radiance and
  display-referred) is judged in both, and :func:`changed_by_space` lists the verdicts that
  differ between them;
* :func:`compact_tables`: the run's tables condensed to at most :data:`MAX_COLUMNS` columns
  of text cells (:data:`TABLES`);
* :func:`read_strips`: per scene, the linear images the reconstruction part saved for the
  page (``verdict/SCENE/``), scored with the metrics' own tonemapping (display PSNR and
  FLIP at the reference's exposure, :func:`score_strip`).
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from reports import paper_figures
from reports.figures import STRIP_FOLDER, STRIP_MANIFEST, safe_stem

#: Most columns of a compact table.
MAX_COLUMNS = 8
#: Our target for ray queries against Embree on incoherent and shadow rays (ours / Embree rays per second).
EMBREE_TARGET = 0.35
#: "About" in the paper's "about 30% less memory": within this many percentage points.
ABOUT_POINTS = 5.0

HOLDS, PARTLY, NOT_REPRODUCED, MET, NOT_MET = "Holds", "Partly", "Not reproduced", "Met", "Not met"
#: The image spaces a claim can be judged in: key -> wording on the page.
SPACES = {"display": "display-referred", "linear": "linear radiance",
          "display-trained": "display-referred, the net trained on displayed images"}


# ------------------------------------------------------------------ the run's tables
class RunTables:
    """The CSV tables of one results folder, read on first use (None for a table that is not there).

    Parameters
    ----------
    out_dir : str or Path
        A results folder (``results/PROFILE``).
    """

    def __init__(self, out_dir: str | Path):
        self.out_dir = Path(out_dir)
        self._tables: dict[str, Any] = {}

    def __call__(self, stem: str):
        """The table ``STEM.csv`` as a pandas DataFrame, or None when it is missing or empty."""
        import pandas as pd

        if stem not in self._tables:
            path = self.out_dir / f"{stem}.csv"
            try:
                frame = pd.read_csv(path)
            except (FileNotFoundError, pd.errors.EmptyDataError):
                frame = None
            self._tables[stem] = frame if frame is not None and len(frame) else None
        return self._tables[stem]

    def production(self) -> dict | None:
        """The stage records of ``kdtrace production`` (``table1_production.json``), or None when not run here."""
        try:
            return json.loads((self.out_dir / "table1_production.json").read_text())["stages"]
        except (OSError, json.JSONDecodeError, KeyError, TypeError):
            return None

    def provenance(self) -> dict:
        """``provenance.json`` of the run ({} when missing or unreadable)."""
        try:
            return json.loads((self.out_dir / "provenance.json").read_text())
        except (OSError, json.JSONDecodeError):
            return {}


# ------------------------------------------------------------------ claims
@dataclasses.dataclass(frozen=True)
class Finding:
    """What the run says about one claim.

    Attributes
    ----------
    ours : str
        Our figures, with units and the image space.
    verdicts : dict
        Image space (a key of :data:`SPACES`, or ``""`` for a claim with one space) -> verdict.
    """

    ours: str
    verdicts: dict[str, str]


@dataclasses.dataclass(frozen=True)
class Claim:
    """One claim of the paper and how a run judges it.

    Attributes
    ----------
    text : str
        The claim, with where the paper makes it.
    paper : str
        The paper's figure.
    evidence : str
        The results file (relative to the results folder) that holds our numbers.
    rule : str
        How the verdict is decided (shown under the claims table).
    judge : callable
        ``judge(tables) -> Finding or None`` (None: not measured in this folder).
    """

    text: str
    paper: str
    evidence: str
    rule: str
    judge: Callable[[RunTables], Finding | None]


def _span(values: Sequence[float], form: str = "{:.2f}", unit: str = "") -> str:
    """``"a–b unit"`` of the smallest and largest value (``"a to b"`` when one is negative; one value when both print the same)."""
    low, high = form.format(min(values)), form.format(max(values))
    joint = " to " if min(values) < 0 else "–"
    return (low if low == high else f"{low}{joint}{high}") + unit


def _grade(values: Sequence[float], holds: Callable[[float], bool], partly: Callable[[float], bool] | None = None) -> str:
    """:data:`HOLDS` when every value holds; :data:`PARTLY` when every value passes ``partly`` (without it: when some
    value holds); else :data:`NOT_REPRODUCED`."""
    if all(holds(v) for v in values):
        return HOLDS
    if (all(partly(v) for v in values) if partly else any(holds(v) for v in values)):
        return PARTLY
    return NOT_REPRODUCED


def _stand_ins(frame, column: str = "scene"):
    """The rows of the paper's scenes' stand-ins (:data:`reports.paper_figures.TABLE1`), or every row when none is there."""
    chosen = frame[frame[column].isin(list(paper_figures.TABLE1))]
    return chosen if len(chosen) else frame


def _paper_reduction() -> list[float]:
    return [100 * (1 - row["local_references"] / row["naive_references"]) for row in paper_figures.TABLE1.values()]


def _judge_references(tables: RunTables) -> Finding | None:
    frame = tables("table1")
    if frame is None:
        return None
    rows = _stand_ins(frame)
    ours = list(100 * rows["reference_reduction"])
    verdict = _grade(ours, lambda v: v >= min(_paper_reduction()), lambda v: v > 0)
    return Finding(f"{_span(ours, '{:.1f}', '%')} fewer references ({len(ours)} scenes)"
                   + _at_production_scale(tables, "triangle_references", "fewer references"), {"": verdict})


def _at_production_scale(tables: RunTables, field: str, what: str) -> str:
    """``"; X% WHAT at N triangles (kdtrace production)"`` from the production run's trees, or ``""`` without one.

    Shown beside a verdict, not graded: the generated scene stands for none of the paper's.
    """
    stages = tables.production()
    if not stages:
        return ""
    naive, local = stages["build-naive"][field], stages["build-local"][field]
    return f"; {100 * (1 - local / naive):.1f}% {what} at {stages['scene']['triangles']:,} triangles (kdtrace production)"


def _judge_memory(tables: RunTables) -> Finding | None:
    frame = tables("table1")
    if frame is None:
        return None
    rows = _stand_ins(frame)
    ours = list(100 * (1 - rows["local_tree_bytes"] / rows["naive_tree_bytes"]))
    target = 100 * paper_figures.MEMORY_SAVING
    return Finding(f"{_span(ours, '{:.1f}', '%')} less tree memory (build arrays)"
                   + _at_production_scale(tables, "tree_bytes", "less"),
                   {"": _grade(ours, lambda v: v >= target - ABOUT_POINTS)})


def _judge_frame_speed(tables: RunTables) -> Finding | None:
    frame = tables("table1")
    if frame is None:
        return None
    ours = list(_stand_ins(frame)["frame_local_over_naive"])
    paper = min(row["naive_frame_seconds"] / row["local_frame_seconds"] for row in paper_figures.TABLE1.values())
    return Finding(f"{_span(ours, '{:.2f}', '×')} (naive / local frame seconds)",
                   {"": _grade(ours, lambda v: v >= paper, lambda v: v > 1.0)})


def _judge_embree(tables: RunTables) -> Finding | None:
    frame = tables("table1")
    if frame is None:
        return None
    incoherent, shadow = list(frame["incoherent_local_over_embree"]), list(frame["occlusion_local_over_embree"])
    agreement = tables("agreement")
    bad = int(frame["unexplained"].sum() + frame["wrong"].sum())
    if agreement is not None:
        bad += int(agreement["unexplained"].sum() + agreement["wrong"].sum())
    met = min(incoherent + shadow) >= EMBREE_TARGET and bad == 0
    return Finding(f"incoherent {_span(incoherent, '{:.2f}', '×')}, shadow {_span(shadow, '{:.2f}', '×')} Embree; "
                   f"{bad} unexplained or wrong hits", {"": MET if met else NOT_MET})


def _judge_throughput(tables: RunTables) -> Finding | None:
    frame = tables("throughput")
    if frame is None:
        return None
    parts = [f"{_span(list(rows['ours / Mitsuba']), '{:.2f}', '×')} at max_depth {depth} (target {rows['target'].iloc[0]:g}×)"
             for depth, rows in frame.groupby("max_depth")]
    met = bool((frame["met"] == "yes").all())
    return Finding("; ".join(parts) + f"; {int((frame['met'] == 'yes').sum())} of {len(frame)} met",
                   {"": MET if met else NOT_MET})


def _per_scene(frame):
    """Table 2's per-scene rows (not the mixed model, not the pooled row)."""
    return frame[(frame["model"] == "per-scene") & (frame["scene"] != "all scenes")]


def _judge_denoiser_psnr(tables: RunTables) -> Finding | None:
    frame = tables("table2")
    if frame is None:
        return None
    rows = _per_scene(frame)
    spaces = {"display": list(rows["display_psnr"]), "linear": list(rows["test_psnr"])}
    good = paper_figures.ACCEPTABLE_PSNR
    return Finding("; ".join(f"{_span(v, unit=' dB')} {SPACES[s]}" for s, v in spaces.items()),
                   {s: _grade(v, lambda x: x > good) for s, v in spaces.items()})


def _judge_against_production(tables: RunTables) -> Finding | None:
    frame = tables("table2")
    if frame is None:
        return None
    rows = _per_scene(frame)
    production = paper_figures.PRODUCTION_DENOISER
    allowed = -20 * math.log10(production["ours_rmse"] / production["production_rmse"])  # the paper's own gap, dB
    spaces = {"display": list(rows["minus_oidn_display"]), "linear": list(rows["minus_oidn"])}
    return Finding("ours − OIDN: " + "; ".join(f"{_span(v, '{:+.2f}', ' dB')} {SPACES[s]}" for s, v in spaces.items()),
                   {s: _grade(v, lambda x: x >= allowed) for s, v in spaces.items()})


def _seen_rows(frame):
    """Table 3's rows of scenes the mixed model was trained on."""
    return frame[~frame["views"].astype(str).str.startswith("all")]


def _judge_mixed_worse(tables: RunTables) -> Finding | None:
    frame = tables("table3")
    if frame is None:
        return None
    rows = _seen_rows(frame)
    spaces = {"display": list(rows["per_scene_display_psnr"] - rows["display_psnr"]), "linear": list(rows["psnr_difference"])}
    return Finding("per-scene − mixed: " + "; ".join(f"{_span(v, '{:+.2f}', ' dB')} {SPACES[s]}" for s, v in spaces.items()),
                   {s: _grade(v, lambda x: x > 0) for s, v in spaces.items()})


def _judge_unseen(tables: RunTables) -> Finding | None:
    frame = tables("table3")
    if frame is None:
        return None
    rows = frame[frame["views"].astype(str).str.startswith("all")]
    if not len(rows):
        return None
    spaces = {"display": list(rows["display_psnr"]), "linear": list(rows["mixed_psnr"])}
    good = paper_figures.ACCEPTABLE_PSNR
    names = ", ".join(str(name).split(" (")[0] for name in rows["scene"])
    return Finding(f"{names}: " + "; ".join(f"{_span(v, unit=' dB')} {SPACES[s]}" for s, v in spaces.items()),
                   {s: _grade(v, lambda x: x < good) for s, v in spaces.items()})


def _judge_superres(tables: RunTables) -> Finding | None:
    frame = tables("table5")
    if frame is None:
        return None
    rows = frame[(frame["split"] == "test") & (frame["data"] != "all scenes")]
    spaces = {"display": list(rows["display_gain_over_bicubic"]), "linear": list(rows["gain_over_bicubic"])}
    if "displayed_gain_over_bicubic" in rows and rows["displayed_gain_over_bicubic"].notna().all():
        # the display-space net against bicubic of the same displayed image (Table 5's documented variant)
        spaces["display-trained"] = list(rows["displayed_gain_over_bicubic"])
    return Finding("ours − bicubic on test photos and renders: "
                   + "; ".join(f"{_span(v, '{:+.2f}', ' dB')} {SPACES[s]}" for s, v in spaces.items()),
                   {s: _grade(v, lambda x: x > 0) for s, v in spaces.items()})


def _judge_network_seconds(tables: RunTables) -> Finding | None:
    frame = tables("table6")
    if frame is None:
        return None
    denoise, superres = list(frame["ours_denoise_s"]), list(frame["ours_superres_s"])
    paper_denoise = min(row["denoise_seconds"] for row in paper_figures.TABLE6.values())
    paper_superres = min(row["superres_seconds"] for row in paper_figures.TABLE6.values())
    threads = frame["threads"].iloc[0] if "threads" in frame else "?"
    holds = max(denoise) <= paper_denoise and max(superres) <= paper_superres
    return Finding(f"denoise {_span(denoise, '{:.3f}', ' s')} ({frame['frame'].iloc[0]}), superresolution "
                   f"{_span(superres, '{:.3f}', ' s')} (to {frame['superres_output'].iloc[0]}); {threads} threads",
                   {"": HOLDS if holds else NOT_REPRODUCED})


def _judge_combined(tables: RunTables) -> Finding | None:
    frame = tables("combined")
    if frame is None:
        return None
    spaces = {"display": list(frame["display_psnr"]), "linear": list(frame["psnr"])}
    good = paper_figures.ACCEPTABLE_PSNR
    return Finding(f"{frame['render_size'].iloc[0]} → {frame['final_size'].iloc[0]}: "
                   + "; ".join(f"{_span(v, unit=' dB')} {SPACES[s]}" for s, v in spaces.items()),
                   {s: _grade(v, lambda x: x > good) for s, v in spaces.items()})


def _speedup_value(cell: str) -> float:
    """The number of a speed-up cell of :func:`reports.error_time_curves.speedup_cell` (``"> 4.1x"`` -> 4.1; "—" -> NaN)."""
    found = re.search(r"[\d.]+(?:e[+-]?\d+)?", cell)
    return float(found.group()) if found else math.nan


def _judge_speedup(tables: RunTables) -> Finding | None:
    from reports.error_time_curves import headline

    frame = tables("error_time")
    provenance = tables.provenance()
    if frame is None or not provenance:
        return None
    config = provenance["config"]
    recon = config["profiles"][provenance["profile"]]["reconstruction_profile"]
    spp = config["reconstruction"]["profiles"][recon]["spp"]
    cells: dict[str, list[str]] = {"display": [], "linear": []}
    for _, points in frame.groupby("scene", sort=False):
        for space, error in (("display", "display_psnr"), ("linear", "psnr")):
            try:
                cells[space].append(headline(points, spp, "kdtrace+denoiser", error=error)["speedup"])
            except (ValueError, KeyError):
                continue
    if not any(cells.values()):
        return None
    low = paper_figures.SPEEDUP_OVER_PATH_TRACERS[0]
    verdicts, texts = {}, []
    for space, found in cells.items():
        values = [v for v in map(_speedup_value, found) if math.isfinite(v)]
        if not values:
            continue
        verdicts[space] = _grade(values, lambda v: v >= low)
        texts.append(f"{_span(values, '{:.3g}', '×')} {SPACES[space]}")
    return Finding(f"ours + denoiser at {spp} spp over Mitsuba at equal PSNR: " + "; ".join(texts), verdicts)


_ACCEPTABLE = f"{paper_figures.ACCEPTABLE_PSNR:.0f} dB"
_PRODUCTION = paper_figures.PRODUCTION_DENOISER
_PRODUCTION_GAP = -20 * math.log10(_PRODUCTION["ours_rmse"] / _PRODUCTION["production_rmse"])
_SOME = "Partly: on some; else Not reproduced"

#: The paper's claims in the order of the page.
CLAIMS = (
    Claim("The local-branch tree stores fewer triangle references than the naive tree (Table 1)",
          _span(_paper_reduction(), "{:.1f}", "% fewer"), "table1.md",
          "Holds: every stand-in scene saves at least the paper's smallest reduction; Partly: every one saves some; "
          "else Not reproduced", _judge_references),
    Claim("… and uses about 30% less memory (abstract)", f"~{100 * paper_figures.MEMORY_SAVING:.0f}% less", "table1.md",
          f"Holds: every stand-in scene within {ABOUT_POINTS:g} points of the paper's saving; {_SOME}", _judge_memory),
    Claim("… and renders faster (Table 1 frame times, naive / local)",
          _span([r["naive_frame_seconds"] / r["local_frame_seconds"] for r in paper_figures.TABLE1.values()], "{:.2f}", "×"),
          "table1.md", "Holds: every stand-in scene at least the paper's smallest speed-up; Partly: every one faster than "
          "the naive tree; else Not reproduced", _judge_frame_speed),
    Claim(f"Ray queries against Embree (our target: ≥ {EMBREE_TARGET}× on incoherent and shadow rays, no unexplained hit; "
          "the paper has no Embree comparison)", "—", "agreement.md",
          f"Met: every scene at least {EMBREE_TARGET}× Embree on incoherent and shadow rays, and 0 unexplained or wrong hits",
          _judge_embree),
    Claim("Path tracer against Mitsuba 3 `path` (our targets, paths/s)", "—", "throughput.md",
          "Met: every scene and depth meets its target", _judge_throughput),
    Claim(f"The per-scene denoiser is well above {_ACCEPTABLE} (Table 2)",
          _span([r["test_psnr"] for k, r in paper_figures.TABLE2.items() if k != "mixed"], unit=" dB"), "table2.md",
          f"Holds: every scene above {_ACCEPTABLE}; {_SOME}; in each image space", _judge_denoiser_psnr),
    Claim(f"The denoiser is comparable to a production denoiser (§6.2: {_PRODUCTION['production']} on Sponza; ours "
          "against OIDN)", f"{_PRODUCTION['ours_rmse']} vs {_PRODUCTION['production_rmse']} RMSE ({_PRODUCTION_GAP:+.2f} dB)",
          "table2.md", f"Holds: ours − OIDN at least the paper's own gap ({_PRODUCTION_GAP:+.2f} dB) on every scene; {_SOME}",
          _judge_against_production),
    Claim("The mixed model is worse than the per-scene models on every scene (Table 3)",
          _span([r["psnr_difference"] for r in paper_figures.TABLE3.values() if "psnr_difference" in r], "{:.2f}",
                " dB worse"), "table3.md", f"Holds: the per-scene model better on every scene; {_SOME}", _judge_mixed_worse),
    Claim(f"The mixed model fails on a scene it never saw (Table 3, below {_ACCEPTABLE})",
          f"{paper_figures.TABLE3['unseen']['test_psnr']} dB ({paper_figures.TABLE3['unseen']['paper_scene']})",
          "table3.md", f"Holds: below {_ACCEPTABLE} on every never-seen scene; {_SOME}", _judge_unseen),
    Claim("Superresolution beats bicubic interpolation (Tables 4–5)", "better except on CBox", "table5.md",
          f"Holds: above bicubic on the test photos and every scene's test views; {_SOME}", _judge_superres),
    Claim("The networks run in seconds on a CPU (Table 6)",
          f"denoise {_span([r['denoise_seconds'] for r in paper_figures.TABLE6.values()], unit=' s')}, superresolution "
          f"{_span([r['superres_seconds'] for r in paper_figures.TABLE6.values()], unit=' s')} (1 core)", "table6.md",
          "Holds: our slowest at most the paper's fastest, for both networks (other machines: only ratios compare); "
          "else Not reproduced", _judge_network_seconds),
    Claim(f"Render at half resolution, denoise, superresolve: above {_ACCEPTABLE} (§6.4)",
          _span([r["estimated_psnr"] for r in paper_figures.COMBINED_ESTIMATES.values()], unit=" dB (estimated)"),
          "combined.md", f"Holds: every scene above {_ACCEPTABLE}; {_SOME}", _judge_combined),
    Claim("1000×–5000× faster than standard path tracers at comparable error (abstract)",
          _span(paper_figures.SPEEDUP_OVER_PATH_TRACERS, "{:.0f}", "×"), "error_time.md",
          f"Holds: every scene at least {paper_figures.SPEEDUP_OVER_PATH_TRACERS[0]:.0f}× faster; {_SOME}", _judge_speedup),
)


def judge(tables: RunTables) -> list[tuple[Claim, Finding | None]]:
    """Every claim of :data:`CLAIMS` with what the run says (None: not measured in this folder).

    A table without a column the claim needs (another version's CSV) counts as not measured.
    """
    findings = []
    for claim in CLAIMS:
        try:
            findings.append((claim, claim.judge(tables)))
        except (KeyError, IndexError, TypeError, ValueError):
            findings.append((claim, None))
    return findings


def verdict_text(finding: Finding | None) -> str:
    """The verdict cell: one verdict, or one per image space when they differ (plain text)."""
    if finding is None:
        return "not measured in this folder"
    distinct = set(finding.verdicts.values())
    if len(distinct) == 1:
        spaces = [SPACES[s] for s in finding.verdicts if s]
        return distinct.pop() + (f" ({' and '.join(spaces)})" if len(spaces) > 1 else "")
    return "; ".join(f"{verdict} {SPACES[space]}" for space, verdict in finding.verdicts.items())


def changed_by_space(findings: Sequence[tuple[Claim, Finding | None]]) -> list[str]:
    """The claims whose display-referred and linear verdicts differ, as sentences."""
    changed = []
    for claim, finding in findings:
        if finding and {"display", "linear"} <= set(finding.verdicts) and finding.verdicts["display"] != finding.verdicts["linear"]:
            changed.append(f"{claim.text}: {finding.verdicts['linear']} by linear radiance, "
                           f"{finding.verdicts['display']} display-referred")
    return changed


# ------------------------------------------------------------------ compact tables
@dataclasses.dataclass(frozen=True)
class Column:
    """One column of a compact table: header (with unit and image space) and how a row fills it."""

    header: str
    value: Callable[[Any], Any]
    form: str = "{:.2f}"


@dataclasses.dataclass(frozen=True)
class TableSpec:
    """A compact table: its title, the CSV it condenses, which rows, and at most :data:`MAX_COLUMNS` columns."""

    title: str
    stem: str
    columns: tuple[Column, ...]
    rows: Callable[[Any], Any] = lambda frame: frame

    def __post_init__(self) -> None:
        if len(self.columns) > MAX_COLUMNS:
            raise ValueError(f"table {self.title!r} has {len(self.columns)} columns, at most {MAX_COLUMNS}")


def _get(column: str) -> Callable[[Any], Any]:
    return lambda row: row.get(column)


TABLES = (
    TableSpec("Denoising, display-referred (Table 2, test views)", "table2", (
        Column("scene", _get("scene"), "{}"), Column("model", _get("model"), "{}"),
        Column("noisy PSNR (dB, display)", _get("noisy_display_psnr")), Column("ours PSNR (dB, display)", _get("display_psnr")),
        Column("OIDN PSNR (dB, display)", _get("oidn_display_psnr")), Column("FLIP ours (display, ↓)", _get("flip"), "{:.3f}"),
        Column("FLIP OIDN (display, ↓)", _get("oidn_flip"), "{:.3f}"))),
    TableSpec("Denoising, linear radiance (Table 2, test views)", "table2", (
        Column("scene", _get("scene"), "{}"), Column("model", _get("model"), "{}"),
        Column("noisy PSNR (dB, linear)", _get("noisy_test_psnr")), Column("ours PSNR (dB, linear)", _get("test_psnr")),
        Column("OIDN PSNR (dB, linear)", _get("oidn_test_psnr")), Column("relMSE ours (HDR, ↓)", _get("relmse"), "{:.3g}"),
        Column("relMSE OIDN (HDR, ↓)", _get("oidn_relmse"), "{:.3g}"))),
    TableSpec("The mixed model on each scene and on an unseen one (Table 3)", "table3", (
        Column("scene", _get("scene"), "{}"), Column("views", _get("views"), "{}"),
        Column("noisy PSNR (dB, display)", _get("noisy_display_psnr")), Column("mixed PSNR (dB, display)", _get("display_psnr")),
        Column("OIDN PSNR (dB, display)", _get("oidn_display_psnr")), Column("mixed PSNR (dB, linear)", _get("mixed_psnr")),
        Column("per-scene − mixed (dB, linear)", _get("psnr_difference"), "{:+.2f}"))),
    TableSpec("Superresolution 2× (Table 5)", "table5", (
        Column("data", _get("data"), "{}"), Column("split", _get("split"), "{}"),
        Column("bicubic PSNR (dB, display)", _get("bicubic_display_psnr")),
        Column("Lanczos PSNR (dB, display)", _get("lanczos_display_psnr")),
        Column("ours PSNR (dB, display)", _get("ours_display_psnr")),
        Column("ours − bicubic (dB, display)", _get("display_gain_over_bicubic"), "{:+.2f}"),
        Column("ours − bicubic (dB, linear)", _get("gain_over_bicubic"), "{:+.2f}"),
        Column("display-trained − its bicubic (dB, display)", _get("displayed_gain_over_bicubic"), "{:+.2f}"))),
    TableSpec("KD-trees (Table 1)", "table1", (
        Column("scene", _get("scene"), "{}"), Column("triangles", _get("triangles"), "{:,.0f}"),
        Column("references saved (%)", lambda r: 100 * r["reference_reduction"], "{:.1f}"),
        Column("tree bytes saved (%)", lambda r: 100 * (1 - r["local_tree_bytes"] / r["naive_tree_bytes"]), "{:.1f}"),
        Column("frame speed local / naive (×)", _get("frame_local_over_naive")),
        Column("incoherent local / Embree (×)", _get("incoherent_local_over_embree")),
        Column("shadow local / Embree (×)", _get("occlusion_local_over_embree")))),
    TableSpec("Path tracer against Mitsuba 3", "throughput", (
        Column("scene", _get("scene"), "{}"), Column("max_depth", _get("max_depth"), "{}"),
        Column("ours (Mpaths/s)", _get("ours Mpaths/s")), Column("Mitsuba (Mpaths/s)", _get("Mitsuba Mpaths/s")),
        Column("ours / Mitsuba (×)", _get("ours / Mitsuba")), Column("target (×)", _get("target"), "{:g}"),
        Column("met", _get("met"), "{}"))),
    TableSpec("Render, denoise, superresolve (§6.4)", "combined", (
        Column("scene", _get("scene"), "{}"), Column("final size (px)", _get("final_size"), "{}"),
        Column("PSNR (dB, display)", _get("display_psnr")),
        Column("denoised + bicubic (dB, display)", _get("bicubic_display_psnr")),
        Column("PSNR (dB, linear)", _get("psnr")), Column("FLIP (display, ↓)", _get("flip"), "{:.3f}"),
        Column("total (s)", _get("total_seconds"), "{:.3f}"))),
    TableSpec("Network seconds (Table 6)", "table6", (
        Column("scene", _get("scene"), "{}"), Column("frame (px)", _get("frame"), "{}"),
        Column("ours denoise (s)", _get("ours_denoise_s"), "{:.3f}"), Column("OIDN (s)", _get("oidn_s"), "{:.3f}"),
        Column("OIDN / ours (×)", _get("oidn_over_ours")), Column("ours SR (s)", _get("ours_superres_s"), "{:.3f}"),
        Column("bicubic (s)", _get("bicubic_s"), "{:.3f}"))),
)


def _cell(value: Any, form: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "—"
    try:
        return form.format(value)
    except (ValueError, TypeError):
        return str(value)


def compact_tables(tables: RunTables) -> list[tuple[TableSpec, list[list[str]] | None]]:
    """Each of :data:`TABLES` with its rows as text cells (None: its CSV is not in the folder or lacks a column)."""
    out = []
    for spec in TABLES:
        frame = tables(spec.stem)
        if frame is None:
            out.append((spec, None))
            continue
        rows = spec.rows(frame).to_dict("records")
        try:
            out.append((spec, [[_cell(column.value(row), column.form) for column in spec.columns] for row in rows]))
        except (KeyError, TypeError):  # a column missing from another version's CSV
            out.append((spec, None))
    return out


# ------------------------------------------------------------------ strips
@dataclasses.dataclass
class StripImage:
    """One image of a strip.

    Attributes
    ----------
    key : str
        ``noisy``, ``ours``, ``mixed``, ``oidn`` or ``reference`` (a plug-in's own key otherwise).
    label : str
        Shown above it.
    file : str
        Its EXR, relative to the results folder.
    image : numpy.ndarray or None
        Linear (H, W, 3); None when the file is missing or unreadable (``problem`` says why).
    metrics : dict
        ``display_psnr`` (dB) and ``flip`` against the reference at the metrics' exposure; empty
        for the reference and for an image that cannot be scored.
    problem : str
        Why the image is not shown ("" when it is).
    """

    key: str
    label: str
    file: str
    image: np.ndarray | None = None
    metrics: dict[str, float] = dataclasses.field(default_factory=dict)
    problem: str = ""


@dataclasses.dataclass
class Strip:
    """One scene's strip: its images in order, the reference last.

    Attributes
    ----------
    scene, view, split, rule : str
        From the strip's manifest (:func:`reports.figures.write_linear_strip`).
    images : list of StripImage
        The reference is the last one.
    exposure : float or None
        The metrics' exposure of the view (:func:`reconstruction.metrics.auto_exposure` of the
        reference); None without a usable reference.
    problem : str
        Why the strip cannot be drawn ("" when it can).
    """

    scene: str
    view: str
    split: str
    rule: str
    images: list[StripImage]
    exposure: float | None = None
    problem: str = ""

    @property
    def reference(self) -> StripImage:
        """The strip's reference image (the last)."""
        return self.images[-1]

    @property
    def stem(self) -> str:
        """The scene as a file name."""
        return safe_stem(self.scene)


def score_strip(strip: Strip) -> Strip:
    """Fill in the strip's exposure and every image's display PSNR and FLIP (:func:`reconstruction.metrics.display_metrics`).

    A missing or unusable reference sets ``strip.problem``; an image that cannot be scored
    (another shape, NaN/inf values) gets a ``problem`` and is not shown.
    """
    from reconstruction.metrics import auto_exposure, display_metrics

    reference = strip.reference
    if reference.image is None:
        strip.problem = f"the reference image is missing ({reference.problem or reference.file})"
        return strip
    try:
        strip.exposure = auto_exposure(reference.image, f"{strip.scene} {strip.view}")
    except ValueError as error:
        strip.problem = str(error)
        return strip
    for item in strip.images[:-1]:
        if item.image is None:
            continue
        try:
            found = display_metrics(item.image, reference.image, strip.exposure)
        except ValueError as error:
            item.problem, item.image = f"cannot be scored: {error}", None
            continue
        item.metrics = {"display_psnr": found["display_psnr"], "flip": found["flip"]}
    return strip


def scene_order(provenance: dict) -> dict[str, int]:
    """File-safe scene name -> its place in the run's profile: reconstruction scenes, then the never-seen ones ({} unknown)."""
    try:
        profile = provenance["config"]["profiles"][provenance["profile"]]
    except (KeyError, TypeError):
        return {}
    names = [*profile.get("reconstruction_scenes", []), profile.get("unseen_scene"), profile.get("far_unseen_scene")]
    return {safe_stem(name): index for index, name in enumerate(n for n in names if n)}


def read_strips(out_dir: str | Path) -> tuple[list[Strip], list[str]]:
    """The strips saved in ``out_dir/verdict/*/strip.json``, scored (:func:`score_strip`), in the run's scene order (:func:`scene_order`).

    Returns
    -------
    strips : list of Strip
        A missing or unreadable EXR leaves its :class:`StripImage` without an image and with a ``problem``.
    problems : list of str
        Manifests that cannot be read, one sentence each.
    """
    from kdtrace.imageio import read_exr

    out_dir = Path(out_dir)
    strips, problems = [], []
    order = scene_order(RunTables(out_dir).provenance())
    manifests = sorted((out_dir / STRIP_FOLDER).glob(f"*/{STRIP_MANIFEST}"),
                       key=lambda path: (order.get(path.parent.name, len(order)), path.parent.name))
    for manifest_path in manifests:
        relative = manifest_path.relative_to(out_dir).as_posix()
        try:
            manifest = json.loads(manifest_path.read_text())
            entries = manifest["images"]
            images = [StripImage(str(e["key"]), str(e["label"]), f"{STRIP_FOLDER}/{manifest_path.parent.name}/{e['file']}")
                      for e in entries]
            strip = Strip(str(manifest["scene"]), str(manifest["view"]), str(manifest.get("split", "")),
                          str(manifest.get("rule", "")), images)
        except (OSError, json.JSONDecodeError, KeyError, TypeError) as error:
            problems.append(f"{relative} cannot be read ({error})")
            continue
        if not images:
            problems.append(f"{relative} lists no image")
            continue
        for item in images:
            path = out_dir / item.file
            if not path.is_file():
                item.problem = f"{item.file} is missing"
                continue
            try:
                item.image = np.asarray(read_exr(path), dtype=np.float64)
            except (OSError, RuntimeError, ValueError) as error:
                item.problem = f"{item.file} cannot be read ({error})"
                continue
            if item.image.ndim != 3 or item.image.shape[2] != 3:
                item.problem, item.image = f"{item.file} is not an RGB image ({item.image.shape})", None
        strips.append(score_strip(strip))
    return strips, problems


