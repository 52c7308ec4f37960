"""Memory checks before large allocations: a job that cannot fit is refused before it starts.

A render, a KD-tree build, a dataset or its training crops each estimate the bytes they will
allocate (an upper bound, documented where it is computed) and call :func:`require_memory`,
which compares it with the memory available now. A refusal names what was asked for, the
bytes it needs and the bytes available, and happens before anything is allocated.
"""

from __future__ import annotations

from pathlib import Path

#: Where Linux reports the memory available to new allocations without swapping.
MEMINFO = Path("/proc/meminfo")


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
