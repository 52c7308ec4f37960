"""Memory checks before large allocations: a job that cannot fit is refused before it starts.

A render, a KD-tree build, a dataset or its training crops each estimate the bytes they will
allocate (an upper bound, documented where it is computed) and call :func:`require_memory`,
which compares it with the memory available now. A refusal names what was asked for, the
bytes it needs and the bytes available, and happens before anything is allocated.

:func:`resident_peak` measures what a call really took: the growth of the process's peak
resident memory around it (Linux's ``VmHWM``, reset first through ``/proc/self/clear_refs``).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

#: Where Linux reports the memory available to new allocations without swapping.
MEMINFO = Path("/proc/meminfo")
#: Where Linux reports this process's resident memory (``VmRSS``) and its peak (``VmHWM``).
STATUS = Path("/proc/self/status")
#: Writing "5" here resets ``VmHWM`` to the current ``VmRSS`` (Linux 4.0 and later).
CLEAR_REFS = Path("/proc/self/clear_refs")

Result = TypeVar("Result")


class InsufficientMemoryError(ValueError):
    """A request (resolution, scene, dataset) needs more memory than is available; nothing was allocated.

    A ``ValueError``: the request is too large for this machine, and the command line reports it
    as a bad argument.
    """


def available_memory() -> int | None:
    """Bytes of memory available to new allocations: ``MemAvailable`` of ``/proc/meminfo``.

    Returns
    -------
    int or None
        None where the file or the field is missing (not Linux, or a kernel before 3.14):
        nothing is refused then.
    """
    try:
        for line in MEMINFO.read_text().splitlines():
            name, _, value = line.partition(":")
            if name == "MemAvailable":
                return int(value.split()[0]) * 1024  # the file counts kB of 1024 bytes
    except (OSError, ValueError, IndexError):
        return None
    return None


def _gib(count: int) -> str:
    return f"{count / 2**30:,.2f} GiB ({count:,} bytes)"


def require_memory(bytes_needed: int, what: str, advice: str = "") -> None:
    """Refuse ``what`` when its ``bytes_needed`` exceed :func:`available_memory`.

    Parameters
    ----------
    bytes_needed : int
        Upper bound of the bytes the job will allocate.
    what : str
        The job, as the start of the message (``"a 512x512 render"``).
    advice : str, optional
        What to change, appended to the message.

    Raises
    ------
    InsufficientMemoryError
        Naming ``what``, ``bytes_needed`` and the bytes available.
    """
    available = available_memory()
    if available is not None and bytes_needed > available:
        raise InsufficientMemoryError(f"{what} needs up to {_gib(bytes_needed)} of memory, but only "
                                      f"{_gib(available)} are available (MemAvailable)"
                                      + (f"; {advice}" if advice else ""))


def resident_memory() -> tuple[int, int]:
    """This process's resident bytes now and at their peak: ``VmRSS`` and ``VmHWM`` of ``/proc/self/status``.

    Raises
    ------
    OSError
        Where the file or the fields are missing (not Linux).
    """
    fields = {}
    for line in STATUS.read_text().splitlines():
        name, _, value = line.partition(":")
        if name in ("VmRSS", "VmHWM"):
            fields[name] = int(value.split()[0]) * 1024  # kB of 1024 bytes
    if len(fields) != 2:
        raise OSError(f"{STATUS} has no VmRSS and VmHWM: resident memory cannot be measured here")
    return fields["VmRSS"], fields["VmHWM"]


def resident_peak(call: Callable[[], Result]) -> tuple[Result, dict[str, float]]:
    """Run ``call`` and measure its seconds and the growth of resident memory it caused.

    The peak is reset to the current resident size first (``/proc/self/clear_refs``), so
    ``peak_bytes`` is the highest resident size during the call minus the size before it:
    every allocation the call touched, numba's and native libraries' included (Python's
    ``tracemalloc`` sees only Python's). ``retained_bytes`` is what is still resident after,
    freed memory that the C allocator keeps for reuse included.

    Returns
    -------
    result
        What ``call`` returned.
    dict
        ``seconds``, ``peak_bytes``, ``retained_bytes`` and ``peak_exact`` (False where the
        peak could not be reset: then ``peak_bytes`` is the process's lifetime peak minus
        the size before the call, an upper bound).
    """
    before, _ = resident_memory()
    try:
        CLEAR_REFS.write_text("5")
        exact = resident_memory()[1] <= before + (1 << 20)
    except OSError:
        exact = False
    started = time.perf_counter()
    result = call()
    seconds = time.perf_counter() - started
    after, peak = resident_memory()
    return result, {"seconds": seconds, "peak_bytes": max(0, peak - before), "retained_bytes": after - before,
                    "peak_exact": exact}
