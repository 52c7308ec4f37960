"""The CI regression gate: a run's gated metrics against the baseline committed in the repository.

How to use::

    kdtrace report --gate                 # run the quick profile, then gate it
    kdtrace gate [--profile quick]        # gate the outputs already in reports/PROFILE/
    kdtrace update-baseline [--profile quick]   # accept the latest run as the new baseline

A run's metrics are the files ``reports/PROFILE/metrics/*.json`` written by the report
parts (:mod:`reports.metrics`); the baseline is ``reports/baseline/PROFILE.json``. Each
metric is compared by its kind:

========  ==========================================================================
kind      fails when
========  ==========================================================================
zero      the run's value is not 0 (whatever the baseline says)
pass      the run's value is false
count     the run's value differs from the baseline's
psnr      it dropped by more than ``[gate] psnr_tolerance_db`` below the baseline
ratio     it dropped below ``baseline * (1 - tolerance)``, the tolerance from ``[gate]``
========  ==========================================================================

A metric in the baseline but not in the run fails ("missing from run"): a part that
stopped reporting something must say so by updating the baseline. A metric in the run
but not in the baseline is listed as "new" and does not fail, so a new report part can
land before its baseline. A metric whose kind changed fails. Absolute seconds are never
gated: only ratios measured within one run.

The baseline file is sorted, indented JSON of ``{"cpu": ..., "profile": ..., "metrics":
{name: {"kind", "value", "note"}}}`` with ratios rounded to 4 significant digits, so that
its diff after ``kdtrace update-baseline`` shows exactly what changed.

One baseline per machine kind (:func:`kdtrace.provenance.cpu_kind`: CPU model and vector
tier). Training the networks with fixed seeds reproduces its PSNRs on one kind (within
0.005 dB on an Intel Xeon), not across kinds: an AMD EPYC run of the same commit, with
bit-identical renders, trained to PSNRs 3.5 dB lower to 0.6 dB higher than the Xeon
baseline (2026-12-01), and "AMD EPYC" VMs come with AVX-512 and bf16 or with AVX2 only
(fp32 training, other Embree kernels). So ``reports/baseline/PROFILE.SLUG.json``, recorded
on the kind whose name gives ``SLUG`` (:func:`cpu_slug`), is used when it exists for the
machine, and ``PROFILE.json`` (whose ``cpu`` says where it was recorded) otherwise;
``update-baseline`` writes the machine's own file when ``PROFILE.json`` was recorded on
another kind.
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import math
import re
from collections.abc import Iterable
from pathlib import Path

from tabulate import tabulate

from kdtrace.cache import atomic_write_bytes
from kdtrace.config import GateConfig
from kdtrace.provenance import cpu_kind
from reports.metrics import Metric, read_metrics

#: Where the committed baselines live, one ``PROFILE.json`` each.
BASELINE_DIR = Path(__file__).resolve().with_name("baseline")
#: Verdicts, in the order the table lists them.
FAIL, MISSING, NEW, OK = "FAIL", "FAIL: missing from run", "new (not in baseline)", "ok"
_ORDER = {FAIL: 0, MISSING: 1, NEW: 2, OK: 3}
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


def baseline_path(profile_name: str, directory: Path | None = None, cpu: str | None = None) -> Path:
    """The committed baseline of a profile (in :data:`BASELINE_DIR` unless ``directory`` is given).

    With ``cpu``, the baseline recorded on that CPU model (``PROFILE.SLUG.json``) when it
    exists, else the profile's general one (``PROFILE.json``).
    """
    directory = Path(BASELINE_DIR if directory is None else directory)
    if cpu is not None:
        specific = directory / f"{profile_name}.{cpu_slug(cpu)}.json"
        if specific.exists():
            return specific
    return directory / f"{profile_name}.json"


def baseline_cpu(path: str | Path) -> str | None:
    """The CPU model a baseline file was recorded on (None when it does not say or does not exist)."""
    path = Path(path)
    if not path.exists():
        return None
    try:
        return json.loads(path.read_text()).get("cpu")
    except (json.JSONDecodeError, AttributeError):
        return None


def read_baseline(path: str | Path) -> dict[str, Metric]:
    """Read a baseline written by :func:`write_baseline`, validating every entry.

    Raises
    ------
    FileNotFoundError
        When there is no baseline (create it with ``kdtrace update-baseline``).
    ValueError
        When the file is not a baseline (bad JSON, wrong layout, unknown kind, bad value).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no baseline {path}; create it from a run with `kdtrace update-baseline`")
    try:
        document = json.loads(path.read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"baseline {path} is not valid JSON ({error})") from error
    if not isinstance(document, dict) or not isinstance(document.get("metrics"), dict):
        raise ValueError(f"baseline {path}: expected an object with a 'metrics' object")
    metrics = []
    for name, entry in document["metrics"].items():
        if not isinstance(entry, dict) or set(entry) - {"kind", "value", "note"} or not {"kind", "value"} <= set(entry):
            raise ValueError(f"baseline {path}: metric {name!r} needs exactly 'kind', 'value' (and optionally 'note')")
        try:
            metrics.append(Metric(name=name, **entry))
        except (TypeError, ValueError) as error:
            raise ValueError(f"baseline {path}: {error}") from error
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
    tolerance = config.tolerance_for(name)
    floor = old * (1.0 - tolerance)
    change = new / old - 1.0 if old else math.inf
    return verdict(f">= {floor:.3g} (-{tolerance:.0%})", new >= floor, f"dropped {-change:.0%}")


def compare(baseline: dict[str, Metric], run: dict[str, Metric], config: GateConfig,
            skip: Iterable[str] = ()) -> list[Verdict]:
    """Compare a run with the baseline, metric by metric (rules in the module docstring).

    Parameters
    ----------
    baseline, run : dict of name -> Metric
    config : GateConfig
        Tolerances.
    skip : iterable of str
        ``fnmatch`` patterns of baseline metrics not expected in this run (e.g. the
        scenes left out by ``--scenes``); they are neither compared nor missing.

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
        if name not in baseline:
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
            f"{counts[MISSING]} missing from the run, {counts[NEW]} new (not in the baseline)")


def run_gate(out_dir: str | Path, profile_name: str, config: GateConfig, baseline: str | Path | None = None,
             skip: Iterable[str] = ()) -> tuple[bool, str]:
    """Gate the run in ``out_dir`` against the profile's baseline and write ``out_dir/gate.md``.

    Parameters
    ----------
    out_dir : str or Path
        The report folder (holding ``metrics/*.json``).
    profile_name : str
        Selects ``reports/baseline/PROFILE.json`` unless ``baseline`` is given.
    config : GateConfig
    baseline : str or Path, optional
        Another baseline file (default: :func:`baseline_path` for this machine's CPU model).
    skip : iterable of str
        Baseline metric patterns not expected in this run (see :func:`compare`).

    Returns
    -------
    (bool, str)
        Whether the gate passed, and the text it printed into ``gate.md`` (table and summary).
    """
    path = Path(baseline) if baseline is not None else baseline_path(profile_name, cpu=cpu_kind())
    verdicts = compare(read_baseline(path), read_run(out_dir), config, skip)
    passed = not any(v.failed for v in verdicts)
    recorded = baseline_cpu(path)
    text = (f"# Regression gate ({profile_name})\n\nBaseline: `{path}` (recorded on {recorded or 'an unrecorded CPU'}; "
            f"this machine: {cpu_kind()}). Ratio tolerance {config.ratio_tolerance:.0%} "
            f"unless overridden ({config.ratio_tolerances or 'no overrides'}); PSNR tolerance "
            f"{config.psnr_tolerance_db} dB.\n\n{format_table(verdicts)}\n\n{summary(verdicts)}\n")
    atomic_write_bytes(Path(out_dir) / "gate.md", text.encode())
    return passed, text


def update_baseline(out_dir: str | Path, profile_name: str, baseline: str | Path | None = None) -> tuple[Path, str]:
    """Rewrite the profile's baseline from the run in ``out_dir``, recording this machine's CPU model.

    Without ``baseline``: ``PROFILE.json`` when it was recorded on this CPU model (or does
    not exist yet), else this model's own ``PROFILE.SLUG.json``.

    Returns
    -------
    (Path, str)
        The baseline written, and a one-line account of what changed (added, removed,
        changed metrics) against the previous baseline.
    """
    cpu = cpu_kind()
    if baseline is not None:
        path = Path(baseline)
    else:
        general = baseline_path(profile_name)
        same_model = not general.exists() or baseline_cpu(general) == cpu
        path = general if same_model else general.with_name(f"{profile_name}.{cpu_slug(cpu)}.json")
    from reports.plugins import is_plugin_metric

    # plug-ins' metrics (kdtrace report --accelerator/--denoiser) belong to that run, never to the baseline
    run = {name: metric for name, metric in read_run(out_dir).items() if not is_plugin_metric(name)}
    previous = read_baseline(path) if path.exists() else {}
    old_text = baseline_document(profile_name, previous) if previous else ""
    write_baseline(path, profile_name, run, cpu)
    stored = read_baseline(path)
    added = sorted(set(stored) - set(previous))
    removed = sorted(set(previous) - set(stored))
    changed = sorted(name for name in set(stored) & set(previous) if stored[name] != previous[name])
    note = (f"{path}: {len(stored)} metrics; {len(added)} added, {len(removed)} removed, {len(changed)} changed"
            + ("" if old_text else " (new baseline)"))
    return path, note

