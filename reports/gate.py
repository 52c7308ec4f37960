"""The CI regression gate: a run's gated metrics against the baselines committed in the repository.

How to use::

    kdtrace report --gate                 # run the quick profile, then gate it
    kdtrace gate [--profile quick]        # gate the outputs already in results/PROFILE/
    kdtrace update-baseline [--profile quick]   # accept the latest run as the new baseline

A run's metrics are the files ``results/PROFILE/metrics/*.json`` written by the report
parts (:mod:`reports.metrics`). Each metric is compared by its kind:

========  ==========================================================================
kind      fails when
========  ==========================================================================
zero      the run's value is not 0 (whatever the baseline says)
pass      the run's value is false
count     the run's value differs from the baseline's
psnr      it dropped by more than ``[gate] psnr_tolerance_db`` below the baseline
flip      it rose by more than ``[gate] flip_tolerance`` above the baseline (lower is better)
ratio     it dropped below ``baseline * (1 - tolerance)``, the tolerance from ``[gate]``
========  ==========================================================================

Two kinds of baseline, in ``reports/baseline/``:

``PROFILE.json``
    Everything that does not depend on the machine: counts, zeros, passes and the PSNRs and FLIPs of
    the committed networks (``models/PROFILE``, evaluated, never retrained by a run). One
    file that every machine kind reads, so a deterministic number can never go stale on a
    kind nobody ran on.
``PROFILE.ratios.SLUG.json``
    Speed ratios measured within one run (ours / Embree, ours / Mitsuba, ...), which do
    depend on the machine: one file per machine kind (:func:`kdtrace.provenance.cpu_kind`,
    ``SLUG`` by :func:`cpu_slug`). On a kind with no such file the ratios are listed as
    "not gated" with the reason; they neither pass nor fail.

A metric in the baseline but not in the run fails ("missing from run"): a part that
stopped reporting something must say so by updating the baseline. A metric in the run
but not in the baseline is listed as "new" and does not fail, so a new report part can
land before its baseline. A metric whose kind changed fails, naming both kinds. Absolute
seconds are never gated: only ratios measured within one run.

The baseline files are sorted, indented JSON of ``{"profile": ..., "metrics": {name:
{"kind", "value", "note"}}}`` (a ratio file also names its ``cpu``) with values rounded to 4
significant digits, so that a diff after ``kdtrace update-baseline`` shows exactly what changed.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import math
import re
from collections.abc import Iterable
from importlib import resources
from pathlib import Path

from tabulate import tabulate

from kdtrace.cache import atomic_write_bytes
from kdtrace.config import GateConfig
from kdtrace.provenance import cpu_kind
from reports.metrics import Metric, read_metrics

#: Where the committed baselines live, one ``PROFILE.json`` each: the package data ``reports/baseline``
#: (declared in pyproject.toml, so an installed wheel has them too); ``--baselines DIR`` overrides it.
BASELINE_DIR = Path(resources.files("reports") / "baseline")
#: Verdicts, in the order the table lists them.
FAIL, MISSING, NEW, NOT_GATED, OK = ("FAIL", "FAIL: missing from run", "new (not in baseline)",
                                     "not gated", "ok")
_ORDER = {FAIL: 0, MISSING: 1, NEW: 2, NOT_GATED: 3, OK: 4}
#: Metric kinds whose values depend on the machine: their baselines are kept per machine kind.
MACHINE_DEPENDENT = frozenset({"ratio"})
#: Significant digits of floating-point values stored in a baseline.
BASELINE_DIGITS = 4


@dataclasses.dataclass(frozen=True)
class Verdict:
    """One row of the gate's table.

    Attributes
    ----------
    name, kind : str
        The metric (the run's kind; the baseline's when missing from the run).
    baseline, now : float, int, bool or None
        The values (None where absent).
    tolerance : str
        What the comparison allowed, in words (``"== 0"``, ``">= 1.23 (-30%)"``, ...).
    verdict : str
        :data:`OK`, :data:`FAIL`, :data:`MISSING` or :data:`NEW`.
    reason : str
        Why it failed (empty when it did not).
    """

    name: str
    kind: str
    baseline: float | int | bool | None
    now: float | int | bool | None
    tolerance: str
    verdict: str
    reason: str = ""

    @property
    def failed(self) -> bool:
        """True for :data:`FAIL` and :data:`MISSING`."""
        return self.verdict in (FAIL, MISSING)


def _by_name(metrics: Iterable[Metric], origin: str) -> dict[str, Metric]:
    result: dict[str, Metric] = {}
    for metric in metrics:
        if metric.name in result:
            raise ValueError(f"{origin}: metric {metric.name!r} appears twice")
        result[metric.name] = metric
    return result


def read_run(out_dir: str | Path) -> dict[str, Metric]:
    """All metrics of a run: every ``out_dir/metrics/*.json``, by name.

    Raises
    ------
    FileNotFoundError
        When the run has no metrics files (nothing was run into ``out_dir``).
    ValueError
        On a malformed file or a name reported by two files.
    """
    files = sorted((Path(out_dir) / "metrics").glob("*.json"))
    if not files:
        raise FileNotFoundError(f"no metrics in {Path(out_dir) / 'metrics'}: run `kdtrace report` first")
    metrics: list[Metric] = []
    for path in files:
        metrics += read_metrics(path)
    return _by_name(metrics, f"{Path(out_dir) / 'metrics'}")


def cpu_slug(cpu: str) -> str:
    """File-name form of a machine kind: ``"AMD EPYC [avx2]"`` -> ``"amd-epyc-avx2"``."""
    return re.sub(r"[^a-z0-9]+", "-", cpu.lower()).strip("-")


def baseline_path(profile_name: str, directory: Path | None = None) -> Path:
    """The profile's machine-independent baseline, ``PROFILE.json`` (in :data:`BASELINE_DIR` by default)."""
    return Path(BASELINE_DIR if directory is None else directory) / f"{profile_name}.json"


def ratio_baseline_path(profile_name: str, cpu: str, directory: Path | None = None) -> Path:
    """The profile's speed ratios recorded on machine kind ``cpu``, ``PROFILE.ratios.SLUG.json``."""
    return Path(BASELINE_DIR if directory is None else directory) / f"{profile_name}.ratios.{cpu_slug(cpu)}.json"


def recorded_kinds(profile_name: str, directory: Path | None = None) -> list[str]:
    """The machine kinds with a speed-ratio baseline of the profile (as their files name them)."""
    directory = Path(BASELINE_DIR if directory is None else directory)
    kinds = []
    for path in sorted(directory.glob(f"{profile_name}.ratios.*.json")):
        try:
            kinds.append(str(json.loads(path.read_text()).get("cpu", path.name)))
        except (json.JSONDecodeError, AttributeError, OSError):
            kinds.append(f"{path.name} (unreadable)")
    return kinds


def _document(path: Path) -> dict:
    if not path.exists():
        raise FileNotFoundError(f"no baseline {path}; create it from a run with `kdtrace update-baseline`")
    try:
        document = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"baseline {path} is not valid JSON ({error})") from error
    except OSError as error:
        raise ValueError(f"baseline {path} cannot be read ({error})") from error
    if not isinstance(document, dict) or not isinstance(document.get("metrics"), dict):
        raise ValueError(f"baseline {path}: expected an object with a 'metrics' object")
    return document


def baseline_cpu(path: str | Path) -> str | None:
    """The machine kind a speed-ratio baseline was recorded on (None when it does not say)."""
    return _document(Path(path)).get("cpu")


def read_baseline(path: str | Path, profile_name: str | None = None,
                  machine_dependent: bool | None = None) -> dict[str, Metric]:
    """Read a baseline written by :func:`write_baseline`, validating every entry.

    Parameters
    ----------
    path : str or Path
    profile_name : str, optional
        When given, the file must have been recorded for this profile.
    machine_dependent : bool, optional
        True: the file must hold only :data:`MACHINE_DEPENDENT` kinds (a per-kind ratio file);
        False: none of them (the shared file). None: not checked.

    Raises
    ------
    FileNotFoundError
        When there is no baseline (create it with ``kdtrace update-baseline``).
    ValueError
        When the file is not a baseline (unreadable, bad JSON, wrong layout, unknown kind, bad
        value), was recorded for another profile, or holds a kind that belongs in the other file.
    """
    path = Path(path)
    document = _document(path)
    if profile_name is not None and document.get("profile") != profile_name:
        raise ValueError(f"baseline {path} was recorded for profile {document.get('profile')!r}, not {profile_name!r}")
    metrics = []
    for name, entry in document["metrics"].items():
        if not isinstance(entry, dict) or set(entry) - {"kind", "value", "note"} or not {"kind", "value"} <= set(entry):
            raise ValueError(f"baseline {path}: metric {name!r} needs exactly 'kind', 'value' (and optionally 'note')")
        try:
            metric = Metric(name=name, **entry)
        except (TypeError, ValueError) as error:
            raise ValueError(f"baseline {path}: {error}") from error
        if machine_dependent is not None and (metric.kind in MACHINE_DEPENDENT) != machine_dependent:
            where = "a per-machine-kind ratio file" if machine_dependent else "the machine-independent baseline"
            raise ValueError(f"baseline {path}: metric {name!r} of kind {metric.kind!r} does not belong in {where}")
        metrics.append(metric)
    return _by_name(metrics, str(path))


def _rounded(value: float | int | bool) -> float | int | bool:
    if isinstance(value, (bool, int)) or value == 0:
        return value
    return round(value, BASELINE_DIGITS - 1 - math.floor(math.log10(abs(value))))


def baseline_document(profile_name: str, metrics: dict[str, Metric], cpu: str | None = None) -> str:
    """The baseline's text: sorted, indented JSON (stable, so diffs show only changes)."""
    entries = {name: {"kind": m.kind, "value": _rounded(m.value), **({"note": m.note} if m.note else {})}
               for name, m in sorted(metrics.items())}
    document = {"profile": profile_name, "metrics": entries, **({"cpu": cpu} if cpu else {})}
    return json.dumps(document, indent=1, sort_keys=True) + "\n"


def write_baseline(path: str | Path, profile_name: str, metrics: dict[str, Metric], cpu: str | None = None) -> Path:
    """Write the baseline atomically (see :func:`baseline_document`)."""
    return atomic_write_bytes(Path(path), baseline_document(profile_name, metrics, cpu).encode())


def _compare_one(name: str, before: Metric, now: Metric, config: GateConfig) -> Verdict:
    kind, old, new = now.kind, before.value, now.value

    def verdict(tolerance: str, ok: bool, reason: str) -> Verdict:
        return Verdict(name, kind, old, new, tolerance, OK if ok else FAIL, "" if ok else reason)

    if before.kind != now.kind:
        return Verdict(name, kind, old, new, "same kind", FAIL, f"kind changed from {before.kind} to {now.kind}")
    if kind == "zero":
        return verdict("== 0", new == 0, f"{new} (must be 0)")
    if kind == "pass":
        return verdict("must pass", new is True, "did not pass")
    if kind == "count":
        return verdict("== baseline", new == old, f"changed by {new - old:+}")
    if kind == "psnr":
        floor = old - config.psnr_tolerance_db
        return verdict(f">= {floor:.2f} dB (-{config.psnr_tolerance_db} dB)", new >= floor,
                       f"dropped {old - new:.2f} dB")
    if kind == "flip":
        ceiling = old + config.flip_tolerance
        return verdict(f"<= {ceiling:.4f} (+{config.flip_tolerance})", new <= ceiling, f"rose {new - old:+.4f}")
    tolerance = config.tolerance_for(name)
    floor = old * (1.0 - tolerance)
    change = new / old - 1.0 if old else math.inf
    return verdict(f">= {floor:.3g} (-{tolerance:.0%})", new >= floor, f"dropped {-change:.0%}")


def compare(baseline: dict[str, Metric], run: dict[str, Metric], config: GateConfig,
            skip: Iterable[str] = (), not_gated: str = "") -> list[Verdict]:
    """Compare a run with the baseline, metric by metric (rules in the module docstring).

    Parameters
    ----------
    baseline, run : dict of name -> Metric
    config : GateConfig
        Tolerances.
    skip : iterable of str
        ``fnmatch`` patterns of baseline metrics not expected in this run (e.g. the
        scenes left out by ``--scenes``); they are neither compared nor missing.
    not_gated : str
        When not empty, the reason the run's :data:`MACHINE_DEPENDENT` metrics cannot be gated
        (no ratio baseline for this machine kind): they are listed as :data:`NOT_GATED`.

    Returns
    -------
    list of Verdict
        Failures first, then missing, new and passing metrics, each group by name.
    """
    skip = tuple(skip)
    verdicts = []
    for name, before in baseline.items():
        if name in run:
            verdicts.append(_compare_one(name, before, run[name], config))
        elif not any(fnmatch.fnmatchcase(name, pattern) for pattern in skip):
            verdicts.append(Verdict(name, before.kind, before.value, None, "present", MISSING,
                                    "in the baseline but not reported by this run"))
    for name, now in run.items():
        if name in baseline:
            continue
        if not_gated and now.kind in MACHINE_DEPENDENT:
            verdicts.append(Verdict(name, now.kind, None, now.value, "-", NOT_GATED, not_gated))
            continue
        absolute = _absolute_verdict(now)
        verdicts.append(absolute if absolute.failed else Verdict(name, now.kind, None, now.value, "-", NEW))
    return sorted(verdicts, key=lambda v: (_ORDER[v.verdict], v.name))


def _absolute_verdict(metric: Metric) -> Verdict:
    """A ``zero`` or ``pass`` metric judged without a baseline (other kinds always pass here)."""
    if metric.kind == "zero" and metric.value != 0:
        return Verdict(metric.name, metric.kind, None, metric.value, "== 0", FAIL, f"{metric.value} (must be 0)")
    if metric.kind == "pass" and metric.value is not True:
        return Verdict(metric.name, metric.kind, None, metric.value, "must pass", FAIL, "did not pass")
    return Verdict(metric.name, metric.kind, None, metric.value, "-", OK)


def absolute_failures(metrics: Iterable[Metric]) -> list[Verdict]:
    """Failed ``zero`` and ``pass`` metrics: correctness failures that need no baseline."""
    return [v for v in map(_absolute_verdict, metrics) if v.failed]


def _show(value: float | int | bool | None) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.4g}"
    return str(value)


def format_table(verdicts: list[Verdict], only_notable: bool = False) -> str:
    """The gate's table (name, kind, baseline, now, tolerance, verdict) as GitHub Markdown.

    ``only_notable`` leaves out the metrics that passed.
    """
    rows = [{"name": v.name, "kind": v.kind, "baseline": _show(v.baseline), "now": _show(v.now),
             "tolerance": v.tolerance, "verdict": v.verdict + (f": {v.reason}" if v.reason and v.verdict == FAIL else "")}
            for v in verdicts if not (only_notable and v.verdict == OK)]
    return tabulate(rows, headers="keys", tablefmt="github", disable_numparse=True) if rows else "(no metrics)"


def summary(verdicts: list[Verdict]) -> str:
    """One line: counts per verdict and PASSED or FAILED."""
    counts = {label: sum(v.verdict == label for v in verdicts) for label in _ORDER}
    failed = counts[FAIL] + counts[MISSING]
    return (f"gate {'FAILED' if failed else 'PASSED'}: {counts[OK]} ok, {counts[FAIL]} failed, "
            f"{counts[MISSING]} missing from the run, {counts[NEW]} new (not in the baseline), "
            f"{counts[NOT_GATED]} not gated")


def _shown(path: Path) -> str:
    """A baseline's path as the gate's page shows it: relative to the repository when inside it."""
    try:
        return str(path.resolve().relative_to(BASELINE_DIR.parents[1]))
    except ValueError:
        return path.name


def read_baselines(profile_name: str, directory: Path | None = None,
                   cpu: str | None = None) -> tuple[dict[str, Metric], str]:
    """The merged baseline for this machine: the shared file's metrics and this kind's ratios.

    Returns
    -------
    metrics : dict of name -> Metric
    ratios : str
        Which speed-ratio baseline was used, or why the ratios are not gated (then the
        ``metrics`` hold no ratio and :func:`compare` is given this text as ``not_gated``).
    """
    cpu = cpu_kind() if cpu is None else cpu
    metrics = read_baseline(baseline_path(profile_name, directory), profile_name, machine_dependent=False)
    ratio_path = ratio_baseline_path(profile_name, cpu, directory)
    if not ratio_path.exists():
        others = ", ".join(recorded_kinds(profile_name, directory)) or "none"
        return metrics, (f"no speed-ratio baseline for this machine kind ({cpu}): {_shown(ratio_path)} does not exist "
                         f"(kinds with one: {others}); record it with `kdtrace update-baseline` after a run on an idle "
                         f"machine of this kind")
    ratios = read_baseline(ratio_path, profile_name, machine_dependent=True)
    recorded = baseline_cpu(ratio_path)
    if recorded != cpu:
        raise ValueError(f"baseline {ratio_path} was recorded on {recorded!r}, not on this machine kind {cpu!r}")
    return {**metrics, **ratios}, ""


def run_gate(out_dir: str | Path, profile_name: str, config: GateConfig, directory: str | Path | None = None,
             skip: Iterable[str] = ()) -> tuple[bool, str]:
    """Gate the run in ``out_dir`` against the profile's baselines and write ``out_dir/gate.md``.

    Parameters
    ----------
    out_dir : str or Path
        The report folder (holding ``metrics/*.json``).
    profile_name : str
        Selects ``PROFILE.json`` and this machine kind's ``PROFILE.ratios.SLUG.json``.
    config : GateConfig
    directory : str or Path, optional
        Folder of the baselines (default :data:`BASELINE_DIR`).
    skip : iterable of str
        Baseline metric patterns not expected in this run (see :func:`compare`).

    Returns
    -------
    (bool, str)
        Whether the gate passed, and the text it printed into ``gate.md`` (table and summary).
    """
    directory = Path(BASELINE_DIR if directory is None else directory)
    cpu = cpu_kind()
    baseline, not_gated = read_baselines(profile_name, directory, cpu)
    verdicts = compare(baseline, read_run(out_dir), config, skip, not_gated)
    passed = not any(v.failed for v in verdicts)
    ratios = (f"speed ratios **not gated**: {not_gated}" if not_gated else
              f"speed ratios against `{_shown(ratio_baseline_path(profile_name, cpu, directory))}`, recorded on this "
              f"machine kind ({cpu}), tolerance {config.ratio_tolerance:.0%} unless overridden "
              f"({config.ratio_tolerances or 'no overrides'})")
    text = (f"# Regression gate ({profile_name})\n\nMachine-independent metrics (counts, zeros, passes, PSNRs and "
            f"FLIPs of the committed networks) against `{_shown(baseline_path(profile_name, directory))}`, one baseline "
            f"for every machine kind, PSNR tolerance {config.psnr_tolerance_db} dB, FLIP tolerance "
            f"+{config.flip_tolerance}; {ratios}.\n\n"
            f"{format_table(verdicts)}\n\n{summary(verdicts)}\n")
    atomic_write_bytes(Path(out_dir) / "gate.md", text.encode())
    return passed, text


def _account(path: Path, previous: dict[str, Metric], stored: dict[str, Metric]) -> str:
    added = sorted(set(stored) - set(previous))
    removed = sorted(set(previous) - set(stored))
    changed = sorted(name for name in set(stored) & set(previous) if stored[name] != previous[name])
    return (f"{_shown(path)}: {len(stored)} metrics; {len(added)} added, {len(removed)} removed, {len(changed)} changed"
            + ("" if previous else " (new baseline)"))


def update_baseline(out_dir: str | Path, profile_name: str,
                    directory: str | Path | None = None) -> tuple[list[Path], str]:
    """Rewrite the profile's baselines from the run in ``out_dir``.

    The machine-independent metrics go to ``PROFILE.json`` (shared by every kind), the speed
    ratios to this machine kind's ``PROFILE.ratios.SLUG.json`` (written only when the run has any).

    Returns
    -------
    (list of Path, str)
        The baselines written, and what changed in each (added, removed, changed metrics).
    """
    from reports.plugins import is_plugin_metric

    directory = Path(BASELINE_DIR if directory is None else directory)
    cpu = cpu_kind()
    # plug-ins' metrics (kdtrace report --accelerator/--denoiser) belong to that run, never to the baseline
    run = {name: metric for name, metric in read_run(out_dir).items() if not is_plugin_metric(name)}
    shared = {name: m for name, m in run.items() if m.kind not in MACHINE_DEPENDENT}
    ratios = {name: m for name, m in run.items() if m.kind in MACHINE_DEPENDENT}
    targets = [(baseline_path(profile_name, directory), shared, None)]
    if ratios:
        targets.append((ratio_baseline_path(profile_name, cpu, directory), ratios, cpu))
    written, notes = [], []
    for path, metrics, recorded_on in targets:
        previous = read_baseline(path) if path.exists() else {}
        write_baseline(path, profile_name, metrics, recorded_on)
        written.append(path)
        notes.append(_account(path, previous, read_baseline(path)))
    return written, "; ".join(notes)
