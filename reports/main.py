"""The main job: run every report part of a profile, index the results, stamp them, gate them.

How to use::

    kdtrace report                          # quick profile, all parts, into results/quick/
    kdtrace report --profile paper --gate   # full scale, then the regression gate
    kdtrace report --scenes car,bunny --parts table1,agreement
    kdtrace report --scenes cbox-original --accelerator my_bvh:make --denoiser bilateral   # plug-ins' rows too

    from reports.main import run_report
    outcome = run_report(config, "quick", Path("results/quick"), gate=True)

The parts (:data:`PARTS`) run in order; each is a module with
``generate(config, profile_name, out_dir, fresh=False, progress=True) -> list[Metric]``
that writes its own tables and plots into ``out_dir`` and its gated metrics to
``out_dir/metrics/PART.json``; a part whose ``generate`` also takes ``accelerators`` or
``denoisers`` gets the plug-ins named by ``--accelerator`` / ``--denoiser``
(:mod:`reports.plugins`). Modules are imported by dotted name only when the run
starts, and all of them are looked up before any work, so a missing one is a clear
error at once. ``--scenes`` restricts the profile's ``scenes`` (and its
``reconstruction_scenes`` to those among them) for every part.

Afterwards the verdict page (:mod:`reports.verdict_page`: ``verdict.md`` and ``verdict.html``, the
paper's claims judged on whatever the folder holds) is written, and ``out_dir/README.md``
links it first, then every file each part wrote, with the notes the
parts raised (:class:`reports.notes.ReportNote`: reused caches, a missing backend such as
Mitsuba falling back to ``scalar_rgb``), and ``provenance.json`` records the profile,
the resolved configuration, the seeds, package versions, CPU model and cores, the date
and the seconds of every part.
"""

from __future__ import annotations

import dataclasses
import importlib
import importlib.util
import inspect
import json
import warnings
from pathlib import Path

from kdtrace.cache import atomic_write_bytes
from kdtrace.config import Config
from kdtrace.provenance import stamp
from kdtrace.timing import timed
from reports.metrics import Metric
from reports.notes import ReportNote
from reports.plugins import check_specs

#: Report parts in the order they run: name -> module with a ``generate`` function.
PARTS = {
    "table1": "reports.table1",
    "agreement": "reports.agreement",
    "reconstruction": "reports.reconstruction_tables",
    "error_time": "reports.error_time",
    "throughput": "reports.throughput",
    "combined": "reports.combined",
    "scaleout": "reports.scaleout",
}
#: Files of the output folder that are bookkeeping rather than results (not linked from the index).
BOOKKEEPING = ("README.md", "provenance.json", "gate.md", "verdict.md", "verdict.html")
#: Folders whose files the index does not list one by one (rows of resumable parts, the verdict page's images).
UNLISTED_FOLDERS = ("rows/", "verdict/")
#: Suffixes of result files the index links (PNG plots are also shown inline).
RESULT_SUFFIXES = (".md", ".csv", ".png", ".json", ".exr")


@dataclasses.dataclass
class PartRun:
    """What one part did: its seconds, metrics, notes and the files it wrote."""

    name: str
    seconds: float
    metrics: list[Metric]
    notes: list[str]
    files: list[str]


@dataclasses.dataclass
class ReportOutcome:
    """The result of :func:`run_report`.

    Attributes
    ----------
    parts : list of PartRun
    correctness_failures : list of str
        Failed ``zero``/``pass`` metrics (unexplained disagreements, failed Z-tests), gate or not.
    gate_passed : bool or None
        The gate's verdict; None when the gate did not run.
    gate_text : str
        The gate's table and summary ("" without the gate).
    """

    parts: list[PartRun]
    correctness_failures: list[str]
    gate_passed: bool | None = None
    gate_text: str = ""

    @property
    def ok(self) -> bool:
        """No correctness failure and no failed gate."""
        return not self.correctness_failures and self.gate_passed is not False


def resolve_parts(parts: list[str] | None = None) -> dict[str, str]:
    """The parts to run (all of :data:`PARTS` by default), each checked to exist.

    Raises
    ------
    ValueError
        For an unknown part name, or a part whose module cannot be found (listing them).
    """
    names = list(PARTS) if parts is None else list(parts)
    unknown = [name for name in names if name not in PARTS]
    if unknown:
        raise ValueError(f"unknown report parts {unknown}; known: {', '.join(PARTS)}")
    missing = [f"{name} ({PARTS[name]})" for name in names if importlib.util.find_spec(PARTS[name]) is None]
    if missing:
        raise ValueError(f"report parts without a module: {', '.join(missing)}; run the others with "
                         f"--parts {','.join(n for n in names if importlib.util.find_spec(PARTS[n]) is not None)}")
    return {name: PARTS[name] for name in names}


def restrict_scenes(config: Config, profile_name: str, scenes: list[str] | None) -> Config:
    """The configuration with the profile limited to ``scenes`` (None: unchanged).

    Raises
    ------
    ValueError
        For a scene name that no scene description has (listing the known names).
    """
    if not scenes:
        return config
    from kdtrace.scenes import list_scenes

    known = list_scenes()
    unknown = sorted(set(scenes) - set(known))
    if unknown:
        raise ValueError(f"unknown scenes {unknown}; available: {', '.join(known)}")
    profile = config.profile(profile_name)
    limited = dataclasses.replace(profile, scenes=tuple(scenes),
                                  reconstruction_scenes=tuple(s for s in profile.reconstruction_scenes if s in scenes),
                                  variant_scenes=tuple(s for s in profile.variant_scenes if s in scenes),
                                  demodulated_scenes=tuple(s for s in profile.demodulated_scenes if s in scenes),
                                  perceptual_scenes=tuple(s for s in profile.perceptual_scenes if s in scenes))
    return dataclasses.replace(config, profiles={**config.profiles, profile_name: limited})


def _snapshot(out_dir: Path) -> dict[str, int]:
    return {str(path.relative_to(out_dir)): path.stat().st_mtime_ns for path in out_dir.rglob("*")
            if path.is_file() and path.suffix in RESULT_SUFFIXES}


def _written(before: dict[str, int], after: dict[str, int]) -> list[str]:
    return sorted(name for name, mtime in after.items()
                  if before.get(name) != mtime and name not in BOOKKEEPING and not name.startswith(UNLISTED_FOLDERS))


def _plugin_arguments(generate, plugins: dict[str, list[str]]) -> dict[str, list[str]]:
    """The plug-in keyword arguments (``accelerators``, ``denoisers``) a part's ``generate`` takes, when given."""
    parameters = inspect.signature(generate).parameters
    return {name: specs for name, specs in plugins.items() if specs and name in parameters}


def _run_part(name: str, module_name: str, config: Config, profile_name: str, out_dir: Path, fresh: bool,
              progress: bool, plugins: dict[str, list[str]] | None = None) -> PartRun:
    from references.llvm import LLVMFallbackWarning

    module = importlib.import_module(module_name)
    before = _snapshot(out_dir)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        metrics, seconds = timed(lambda: module.generate(config, profile_name, out_dir, fresh=fresh, progress=progress,
                                                         **_plugin_arguments(module.generate, plugins or {})))
    notes = []
    for warning in caught:
        text = str(warning.message)
        if issubclass(warning.category, (ReportNote, LLVMFallbackWarning)):
            if text not in notes:
                notes.append(text)
        else:
            warnings.warn_explicit(warning.message, warning.category, warning.filename, warning.lineno)
    return PartRun(name, seconds, list(metrics), notes, _written(before, _snapshot(out_dir)))


def _link(name: str) -> str:
    return f"![{name}]({name})\n" if name.endswith(".png") else f"- [{name}]({name})"


def _index(parts: list[PartRun], profile_name: str, provenance: dict, gate_line: str, others: list[str]) -> str:
    from reports.verdict_page import INDEX_LINE

    host, versions = provenance["machine"], provenance["versions"]
    lines = [f"# kdtrace report: {profile_name} profile\n", INDEX_LINE,
             f"{host['date']} on {host['cpu']} ({host['cores']} cores, {host['numba_threads']} numba threads), "
             f"Python {host['python']}. Versions: " + ", ".join(f"{k} {v}" for k, v in versions.items()) + ". "
             "Seeds: " + ", ".join(f"{k} {v}" for k, v in provenance["seeds"].items()) + ". "
             "The resolved configuration is in [provenance.json](provenance.json).\n"]
    if gate_line:
        lines.append(f"Regression gate: **{gate_line}** ([gate.md](gate.md)).\n")
    for part in parts:
        lines.append(f"## {part.name}\n")
        lines.append(f"{part.seconds:.0f} s, {len(part.metrics)} gated metrics.\n")
        lines += [f"> **Note:** {note}\n" for note in part.notes]
        lines += [_link(name) for name in part.files]
        lines.append("")
    if others:
        lines.append("## Earlier results in this folder (not written by this run)\n")
        lines += [_link(name) for name in others]
    return "\n".join(lines) + "\n"


def run_report(config: Config, profile_name: str, out_dir: str | Path, scenes: list[str] | None = None,
               fresh: bool = False, gate: bool = False, parts: list[str] | None = None,
               progress: bool = True, accelerators: list[str] | tuple[str, ...] = (),
               denoisers: list[str] | tuple[str, ...] = ()) -> ReportOutcome:
    """Run the report parts of a profile, then write the index and provenance, and gate if asked.

    Parameters
    ----------
    config : Config
        Resolved configuration.
    profile_name : str
        A profile of the configuration (an unknown name lists the known ones).
    out_dir : str or Path
        Output folder (``results/PROFILE`` from the command line).
    scenes : list of str, optional
        Limit the profile's scenes (see :func:`restrict_scenes`).
    fresh : bool
        Passed to every part: recompute instead of reusing finished results.
    gate : bool
        Compare the metrics with the profile's baselines afterwards
        (:func:`reports.gate.run_gate`); baseline metrics of scenes left out are skipped.
    parts : list of str, optional
        Names from :data:`PARTS` (default: all, in order).
    progress : bool
        Progress bars and per-part summaries on the terminal.
    accelerators, denoisers : sequence of str
        Plug-in specs (``--accelerator`` / ``--denoiser``; :mod:`reports.plugins`): passed to
        the parts that take them (Table 1 and agreement; Tables 2 and 6 and the error-time
        sweep). Every spec is resolved first, so one that cannot be imported fails before
        any work; a plug-in that raises or returns invalid output is recorded in its rows.

    Returns
    -------
    ReportOutcome
    """
    from reports import gate as gate_module
    from reports.gate import absolute_failures
    from reports.verdict_page import write_verdict

    profile = config.profile(profile_name)
    config = restrict_scenes(config, profile_name, scenes)
    modules = resolve_parts(parts)
    plugins = {"accelerators": list(accelerators), "denoisers": list(denoisers)}
    check_specs(plugins["accelerators"], plugins["denoisers"])  # an unknown or unimportable plug-in fails first
    if gate:
        gate_module.read_baselines(profile_name)  # a missing or malformed baseline fails first
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    runs = []
    for name, module_name in modules.items():
        if progress:
            print(f"== {name} ({module_name})", flush=True)
        run = _run_part(name, module_name, config, profile_name, out_dir, fresh, progress, plugins)
        runs.append(run)
        if progress:
            print(f"== {name}: {run.seconds:.0f} s, {len(run.metrics)} metrics, wrote {', '.join(run.files) or 'nothing'}")
            for note in run.notes:
                print(f"   note: {note}")

    outcome = ReportOutcome(runs, [f"{v.name}: {v.reason}" for v in absolute_failures(m for r in runs for m in r.metrics)])
    if gate:
        left_out = sorted((set(profile.scenes) | set(profile.reconstruction_scenes)) - set(config.profile(profile_name).scenes))
        outcome.gate_passed, outcome.gate_text = gate_module.run_gate(
            out_dir, profile_name, config.gate, skip=[f"*/{scene}/*" for scene in left_out])

    seeds = {"profile": profile.seed, "render": config.render.seed, "embree_check": config.embree_check.seed}
    if profile.reconstruction_profile in config.reconstruction.profiles:
        seeds["reconstruction"] = config.reconstruction.profile(profile.reconstruction_profile).seed
    provenance = stamp(config.to_dict(), profile=profile_name, seeds=seeds, fresh=fresh, plugins=plugins,
                       parts={r.name: {"seconds": round(r.seconds, 1), "notes": r.notes, "files": r.files} for r in runs})
    atomic_write_bytes(out_dir / "provenance.json", json.dumps(provenance, indent=1, default=str).encode())
    write_verdict(out_dir, profile_name)
    gate_line = outcome.gate_text.strip().splitlines()[-1] if gate else ""
    written = {name for run in runs for name in run.files}
    others = _written({}, {name: 0 for name in _snapshot(out_dir) if name not in written})
    atomic_write_bytes(out_dir / "README.md", _index(runs, profile_name, provenance, gate_line, others).encode())
    return outcome
