"""Plug-in accelerators and denoisers in the report (``kdtrace report --accelerator NAME --denoiser NAME``).

A plug-in is named as :mod:`kdtrace.plugins` accepts it (an entry-point short name or
``package.module:factory``); both options repeat and take comma-separated lists, as the
benchmarks' ``--bench-accelerator`` / ``--bench-denoiser`` (:func:`parse_specs`).

Where they appear:

* accelerators: Table 1 (:mod:`reports.table1`, one row per plug-in and scene, cached
  in ``rows/table1-plugins/``) and the agreement part (:mod:`reports.agreement`, from
  those rows);
* denoisers: Tables 2 and 6 (:mod:`reports.reconstruction_tables`) and the
  error-against-time sweep as the method ``kdtrace+SPEC`` (:mod:`reports.error_time`,
  cached in ``rows/error_time-plugins/``).

A plug-in's metrics are named ``PART/SCENE/plugin:SPEC/QUANTITY`` (:func:`metric_name`);
they are never written into a baseline (:func:`is_plugin_metric`, used by
:func:`reports.gate.update_baseline`), so the gate lists them as "new". Their ``zero``
metrics (wrong hits, unexplained disagreements, ``failed``) are judged absolutely: a
plug-in that is wrong, raises or returns invalid output fails the run, which the user
asked for by naming it. A failure is caught per plug-in (and scene) and recorded in its
row as ``failed: MESSAGE`` (the :class:`kdtrace.plugins.PluginError` message naming the
plug-in); our own rows are measured as without plug-ins, under unchanged cache keys.
"""

from __future__ import annotations

import hashlib
import importlib
import re
import sys
from collections.abc import Iterable, Sequence
from pathlib import Path

from kdtrace.plugins import ACCELERATOR_GROUP, DENOISER_GROUP, PluginError, resolve_factory

#: Segment of a plug-in's metric names, before its spec.
METRIC_PREFIX = "plugin:"
#: Row text of a plug-in that raised or returned invalid output.
FAILED = "failed: "


def parse_specs(values: Iterable[str] | None) -> list[str]:
    """Specs from repeated, comma-separated option values, in order, without repeats."""
    specs: list[str] = []
    for value in values or ():
        for spec in value.split(","):
            spec = spec.strip()
            if spec and spec not in specs:
                specs.append(spec)
    return specs


def check_specs(accelerators: Sequence[str], denoisers: Sequence[str]) -> None:
    """Resolve every spec's factory before any work (without calling it).

    Raises
    ------
    PluginError
        A spec that cannot be imported or is not registered (the command line exits 2).
    """
    for group, specs in ((ACCELERATOR_GROUP, accelerators), (DENOISER_GROUP, denoisers)):
        for spec in specs:
            resolve_factory(spec, group)


def fingerprint(spec: str, group: str) -> str:
    """A hash of the source file that defines the plug-in's factory (part of cached rows' keys).

    An edited plug-in is measured again. Empty when the factory cannot be resolved or its
    module has no source file (its rows are then keyed by the spec alone).
    """
    try:
        factory = resolve_factory(spec, group)
    except PluginError:
        return ""
    try:
        module = sys.modules.get(factory.__module__) or importlib.import_module(factory.__module__)
    except (AttributeError, TypeError, ImportError):
        return ""
    path = getattr(module, "__file__", None)
    if not path or not Path(path).is_file():
        return ""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def slug(spec: str) -> str:
    """A file name for the spec: its safe characters and a short hash (distinct specs, distinct names)."""
    safe = re.sub(r"[^A-Za-z0-9_.-]+", "_", spec).strip("_")[:60]
    return f"{safe}-{hashlib.sha256(spec.encode()).hexdigest()[:8]}"


def metric_name(part: str, scene: str, spec: str, quantity: str) -> str:
    """``PART/SCENE/plugin:SPEC/QUANTITY``."""
    return f"{part}/{scene}/{METRIC_PREFIX}{spec}/{quantity}"


def is_plugin_metric(name: str) -> bool:
    """Whether a metric name is a plug-in's (see :func:`metric_name`)."""
    return any(part.startswith(METRIC_PREFIX) for part in name.split("/")[1:-1])


def failure(error: Exception) -> str:
    """The row text of a failed plug-in: ``failed: MESSAGE``."""
    return FAILED + str(error)
