"""What produced a result: machine, package versions, date — stamped on every result file."""

from __future__ import annotations

import datetime
import os
import platform
from importlib import metadata

PACKAGES = ("kdtrace", "numpy", "numba", "embreex", "mitsuba", "drjit", "torch", "pyoidn", "scikit-image", "pandas")


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (Linux), else ``platform.processor()``."""
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def package_versions() -> dict[str, str]:
    """Installed versions of the packages results depend on ("absent" when missing)."""
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "absent"
    return versions


def machine() -> dict[str, object]:
    """CPU model, logical cores, numba threads, OS, Python and the UTC date."""
    import numba

    return {
        "cpu": cpu_model(),
        "cores": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def stamp(config: dict, **extra: object) -> dict[str, object]:
    """The provenance record written beside every result."""
    return {"machine": machine(), "versions": package_versions(), "config": config, **extra}
