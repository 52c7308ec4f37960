"""Gated metrics: what each report generator hands to the CI regression gate.

Every generator of ``kdtrace report`` returns a list of :class:`Metric` and writes it with
:func:`write_metrics` to ``OUT_DIR/metrics/GENERATOR.json``. The gate
(:mod:`reports.gate`) compares these files with the committed baseline. A metric's
``kind`` says how it is compared:

``ratio``
    A speed ratio measured within one run (ours/Embree, local/naive, ours/Mitsuba,
    ours/OIDN, ...), higher is better; fails when it drops by more than the configured
    relative tolerance. Absolute seconds are never gated.
``psnr``
    A PSNR in dB with fixed seeds, higher is better; fails when it drops by more than the
    configured dB tolerance.
``flip``
    A mean FLIP error in [0, 1] with fixed seeds, lower is better; fails when it rises by more
    than the configured absolute tolerance.
``count``
    An integer that must equal the baseline exactly (e.g. a parameter count).
``zero``
    Must be 0 (e.g. unexplained Embree disagreements).
``pass``
    Must be true (e.g. a Mitsuba Z-test).

Names are stable paths, ``TABLE/SCENE/QUANTITY`` (e.g. ``table1/crytek-sponza/local_over_embree_primary``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Iterable
from pathlib import Path

from kdtrace.cache import atomic_write_bytes

#: The kinds a metric may have (see the module docstring).
KINDS = ("ratio", "psnr", "flip", "count", "zero", "pass")


@dataclasses.dataclass(frozen=True)
class Metric:
    """One gated number.

    Attributes
    ----------
    name : str
        Stable identifier, ``TABLE/SCENE/QUANTITY``.
    kind : str
        One of :data:`KINDS`.
    value : float, int or bool
        The measured value (a finite number, or a bool for ``pass``).
    note : str
        Free text shown in the gate's table (units, what was compared).
    """

    name: str
    kind: str
    value: float | int | bool
    note: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"metric {self.name!r}: kind {self.kind!r} is not one of {KINDS}")
        if self.kind == "pass":
            if not isinstance(self.value, bool):
                raise ValueError(f"metric {self.name!r}: a 'pass' metric needs a bool, got {self.value!r}")
        elif isinstance(self.value, bool) or not isinstance(self.value, (int, float)) or not math.isfinite(self.value):
            raise ValueError(f"metric {self.name!r}: needs a finite number, got {self.value!r}")


def write_metrics(out_dir: str | Path, generator: str, metrics: Iterable[Metric]) -> Path:
    """Write ``out_dir/metrics/GENERATOR.json`` atomically and return its path."""
    metrics = list(metrics)
    names = [m.name for m in metrics]
    if len(set(names)) != len(names):
        raise ValueError(f"{generator}: duplicate metric names {sorted({n for n in names if names.count(n) > 1})}")
    path = Path(out_dir) / "metrics" / f"{generator}.json"
    atomic_write_bytes(path, json.dumps([dataclasses.asdict(m) for m in metrics], indent=1).encode())
    return path


def read_metrics(path: str | Path) -> list[Metric]:
    """Read a file written by :func:`write_metrics` (validating every entry)."""
    try:
        entries = json.loads(Path(path).read_text())
    except json.JSONDecodeError as error:
        raise ValueError(f"{path}: not a metrics file ({error})") from error
    if not isinstance(entries, list):
        raise ValueError(f"{path}: not a metrics file (expected a list)")
    return [Metric(**entry) for entry in entries]
