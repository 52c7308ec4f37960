"""What produced a result: machine, package versions, date — stamped on every result file."""

from __future__ import annotations

import datetime
import os
import platform
from importlib import metadata

PACKAGES = ("kdtrace", "numpy", "numba", "embreex", "mitsuba", "drjit", "torch", "pyoidn", "scikit-image", "pandas")


def _cpuinfo(field: str) -> str | None:
    """The first value of ``field`` in /proc/cpuinfo (None off Linux or when absent)."""
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith(field):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def cpu_model() -> str:
    """CPU model name from /proc/cpuinfo (Linux), else ``platform.processor()``."""
    return _cpuinfo("model name") or platform.processor() or "unknown"


#: Vector extensions that change results, widest first: bfloat16 support decides whether the
#: networks train under bf16 autocast, and the ISA which kernels Embree and oneDNN pick.
_ISA_TIERS = (("amx", ("amx_tile", "amx_bf16")), ("avx512-bf16", ("avx512f", "avx512_bf16")),
              ("avx512", ("avx512f",)), ("avx2", ("avx2",)))


def isa_tier(flags: set[str]) -> str:
    """The widest tier of :data:`_ISA_TIERS` whose flags (``/proc/cpuinfo`` names) are all in
    ``flags``; ``"generic"`` when none is."""
    return next((tier for tier, needed in _ISA_TIERS if flags.issuperset(needed)), "generic")


def cpu_isa() -> str:
    """This CPU's vector tier (:func:`isa_tier` of its ``/proc/cpuinfo`` flags; ``"generic"`` off Linux)."""
    return isa_tier(set((_cpuinfo("flags") or "").split()))


def cpu_kind() -> str:
    """CPU model and vector tier, e.g. ``"AMD EPYC [avx2]"``: one machine kind for the gate's
    baselines. The model name alone is not enough: VMs sold as "AMD EPYC" come with and
    without AVX-512, and they train the networks differently (bf16 or fp32)."""
    return f"{cpu_model()} [{cpu_isa()}]"


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
    """CPU model and vector tier, logical cores, numba threads, allocator, OS, Python and the UTC date."""
    import numba

    from kdtrace.allocator import allocator_policy

    return {
        "cpu": cpu_model(),
        "cpu_isa": cpu_isa(),
        "cores": os.cpu_count(),
        "numba_threads": numba.get_num_threads(),
        "allocator": allocator_policy(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
    }


def stamp(config: dict, **extra: object) -> dict[str, object]:
    """The provenance record written beside every result."""
    return {"machine": machine(), "versions": package_versions(), "config": config, **extra}
