"""Find a usable LLVM for Dr.Jit and choose the Mitsuba variant of the references.

drjit 1.5 crashes with Debian's default LLVM 15; LLVM 19 (Debian package
``libllvm19``, installed by ``scripts/setup-llvm.sh``) works. Dr.Jit loads the library
named by ``DRJIT_LIBLLVM_PATH`` when its LLVM backend starts, so the variable must be
set *before* ``mitsuba``/``drjit`` are imported; :func:`activate_variant` does that.

Whether a variant really renders is checked by :func:`probe_variant` in a child
process, because a bad LLVM can abort the process (a crash, not an exception). When
``llvm_ad_rgb`` is unusable we fall back to ``scalar_rgb`` with a
:class:`LLVMFallbackWarning` saying why; nothing here raises for a missing LLVM.

Usage::

    variant = activate_variant()   # "llvm_ad_rgb" or "scalar_rgb"; mitsuba is ready
"""

from __future__ import annotations

import os
import subprocess
import sys
import warnings
from pathlib import Path

#: Where Debian's ``libllvm19`` puts the library, searched in this order.
LLVM_DIRECTORIES = (Path("/usr/lib/llvm-19/lib"), Path("/usr/lib/x86_64-linux-gnu"))
#: File names of LLVM 19 shared libraries (``libLLVM.so.19.1``, ``libLLVM-19.so``).
LLVM_PATTERNS = ("libLLVM.so.19*", "libLLVM-19.so*")
#: Environment variable Dr.Jit reads to locate ``libLLVM``.
LLVM_ENV = "DRJIT_LIBLLVM_PATH"
LLVM_VARIANT = "llvm_ad_rgb"
SCALAR_VARIANT = "scalar_rgb"
#: Variants the converter supports (both are RGB, so materials map one to one).
SUPPORTED_VARIANTS = (LLVM_VARIANT, SCALAR_VARIANT)
#: Seconds a probe may take (first LLVM start compiles kernels: a few seconds).
PROBE_TIMEOUT = 180.0

# Renders a 4x4 image of a sphere under a constant sky: exercises the JIT, the ray
# tracer and the film. Prints "ok" only when the pixels are finite and positive.
_PROBE_SCRIPT = """
import sys
import numpy as np
import mitsuba as mi
mi.set_variant(sys.argv[1])
scene = mi.load_dict({
    "type": "scene",
    "integrator": {"type": "path", "max_depth": 3},
    "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at(
        origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": 4, "height": 4}},
    "sphere": {"type": "sphere"},
    "sky": {"type": "constant"},
})
image = np.array(mi.render(scene, spp=2))
print("ok" if np.all(np.isfinite(image)) and image.mean() > 0 else "bad image")
"""

_probe_results: dict[tuple[str, str | None], tuple[bool, str]] = {}


class LLVMFallbackWarning(UserWarning):
    """``llvm_ad_rgb`` is unusable; references are rendered with ``scalar_rgb``."""


def find_llvm(directories: tuple[Path, ...] = LLVM_DIRECTORIES) -> Path | None:
    """Path of an LLVM 19 shared library, or None when none is installed.

    Parameters
    ----------
    directories : tuple of Path
        Folders searched in order (default :data:`LLVM_DIRECTORIES`).

    Returns
    -------
    Path or None
        The first ``libLLVM.so.19*`` / ``libLLVM-19.so*`` file found.
    """
    for directory in directories:
        for pattern in LLVM_PATTERNS:
            found = sorted(path for path in directory.glob(pattern) if path.is_file())
            if found:
                return found[0]
    return None


def llvm_library() -> str | None:
    """The LLVM library Dr.Jit should use: ``$DRJIT_LIBLLVM_PATH`` if set, else :func:`find_llvm`."""
    if os.environ.get(LLVM_ENV):
        return os.environ[LLVM_ENV]
    found = find_llvm()
    return None if found is None else str(found)


def probe_variant(variant: str, libllvm: str | None, timeout: float = PROBE_TIMEOUT) -> tuple[bool, str]:
    """Check in a child process that ``variant`` renders a tiny image.

    Parameters
    ----------
    variant : str
        Mitsuba variant name.
    libllvm : str or None
        Value of ``DRJIT_LIBLLVM_PATH`` for the child (None: leave it unset).
    timeout : float
        Seconds before the probe counts as failed.

    Returns
    -------
    (bool, str)
        Whether the variant works, and why not (empty when it works). Results are
        remembered per (variant, library) for the life of the process.
    """
    if (variant, libllvm) in _probe_results:
        return _probe_results[(variant, libllvm)]
    environment = {key: value for key, value in os.environ.items() if key != LLVM_ENV}
    if libllvm is not None:
        environment[LLVM_ENV] = libllvm
    try:
        done = subprocess.run(
            [sys.executable, "-c", _PROBE_SCRIPT, variant],
            env=environment, capture_output=True, text=True, timeout=timeout,
        )
    except subprocess.TimeoutExpired:
        result = (False, f"probe of {variant} timed out after {timeout:.0f} s")
    else:
        lines = (done.stdout + done.stderr).strip().splitlines()
        if done.returncode == 0 and lines[-1:] == ["ok"]:
            result = (True, "")
        else:
            last = lines[-1] if lines else "no output"
            result = (False, f"probe of {variant} exited with code {done.returncode}: {last}")
    _probe_results[(variant, libllvm)] = result
    return result


def select_variant(requested: str | None = None) -> tuple[str, str | None]:
    """Choose the variant to render with, falling back to ``scalar_rgb`` with a warning.

    Parameters
    ----------
    requested : {"llvm_ad_rgb", "scalar_rgb"} or None
        None prefers ``llvm_ad_rgb`` when a usable LLVM is present.

    Returns
    -------
    (str, str or None)
        The variant and the LLVM library to put in ``DRJIT_LIBLLVM_PATH`` (None for
        ``scalar_rgb``).

    Raises
    ------
    ValueError
        For a variant other than ``llvm_ad_rgb`` or ``scalar_rgb``.
    """
    if requested is not None and requested not in SUPPORTED_VARIANTS:
        raise ValueError(f"unsupported Mitsuba variant {requested!r}; choose one of {SUPPORTED_VARIANTS}")
    if requested == SCALAR_VARIANT:
        return SCALAR_VARIANT, None
    libllvm = llvm_library()
    if libllvm is None:
        reason = "no libLLVM.so.19* found in " + ", ".join(map(str, LLVM_DIRECTORIES))
        reason += " (run scripts/setup-llvm.sh, or set DRJIT_LIBLLVM_PATH)"
    else:
        works, reason = probe_variant(LLVM_VARIANT, libllvm)
        if works:
            return LLVM_VARIANT, libllvm
        reason = f"{LLVM_ENV}={libllvm}: {reason}"
    warnings.warn(f"Mitsuba {LLVM_VARIANT} unusable, falling back to {SCALAR_VARIANT} (much slower): {reason}",
                  LLVMFallbackWarning, stacklevel=2)
    return SCALAR_VARIANT, None


def activate_variant(requested: str | None = None) -> str:
    """Select a variant, export ``DRJIT_LIBLLVM_PATH``, import Mitsuba and set the variant.

    Parameters
    ----------
    requested : {"llvm_ad_rgb", "scalar_rgb"} or None
        As in :func:`select_variant`.

    Returns
    -------
    str
        The active variant.

    Notes
    -----
    Dr.Jit reads ``DRJIT_LIBLLVM_PATH`` once, when its LLVM backend starts; if that
    already happened in this process with another library, the new value is ignored.
    An in-process failure to set the LLVM variant also falls back to ``scalar_rgb``.
    """
    variant, libllvm = select_variant(requested)
    if libllvm is not None:
        os.environ[LLVM_ENV] = libllvm
    import mitsuba as mi

    try:
        mi.set_variant(variant)
    except (ImportError, RuntimeError) as error:
        warnings.warn(f"Mitsuba {variant} failed in this process, falling back to {SCALAR_VARIANT}: {error}",
                      LLVMFallbackWarning, stacklevel=2)
        variant = SCALAR_VARIANT
        mi.set_variant(variant)
    return variant
