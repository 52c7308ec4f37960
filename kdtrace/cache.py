"""Content-addressed on-disk cache with atomic writes and claims.

Artefacts (meshes, KD-trees, dataset views, references, networks) are stored under names
made of a SHA-256 key of everything they depend on. Writes go to a temporary file in the
same directory and are renamed into place, so an interrupted run never leaves a
half-written artefact behind. A write that fills the disk or the quota raises
:class:`DiskFullError`, naming the file, the bytes it needs and the bytes free.

Several processes may share one cache (a report while a benchmark runs, Dask workers,
two users): :func:`compute_once` makes the first one to miss an artefact **claim** it
(an exclusive ``fcntl`` lock on a file in ``.locks/`` of the cache, through the ``filelock`` package) while
the others wait and then load what it wrote. The operating system drops the lock of a
process that dies, so a killed holder never blocks anyone; a holder that hangs is given
up on after ``[cache] claim_timeout_seconds`` and the waiter computes the artefact itself
with a warning (both write atomically, so nothing is lost, the work is only done twice).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import tempfile
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from filelock import FileLock, Timeout

from kdtrace.config import DEFAULT_CONFIG


def cache_root() -> Path:
    """The cache directory: ``$KDTRACE_CACHE`` or the configured default."""
    return Path(os.environ.get("KDTRACE_CACHE", DEFAULT_CONFIG.cache.directory))


class ClaimWarning(UserWarning):
    """Another process held an artefact's claim past the timeout; it is computed here as well."""


def claim_lock_path(path: str | Path) -> Path:
    """The lock file of the artefact at ``path``: ``cache_root()/.locks/<hash of its absolute path>.lock``.

    Kept apart from the artefacts, so that their folders hold only artefacts (lock files are
    never deleted: unlinking a lock another process is waiting on would let a third take a new one).
    """
    return cache_root() / ".locks" / f"{hashlib.sha256(str(Path(path).absolute()).encode()).hexdigest()[:32]}.lock"


@contextmanager
def claim(path: str | Path, timeout: float | None = None) -> Iterator[bool]:
    """Hold the exclusive claim on the artefact at ``path`` for the duration of the block.

    Parameters
    ----------
    path : str or Path
        The artefact (file or folder); its lock file is :func:`claim_lock_path`.
    timeout : float, optional
        Seconds to wait for another holder (default ``[cache] claim_timeout_seconds``).

    Yields
    ------
    bool
        True when the claim is held; False when the wait timed out (a :class:`ClaimWarning`
        names the lock) or the lock file cannot be made (a read-only or full cache), and the
        block runs without it.
    """
    path = Path(path).absolute()
    timeout = DEFAULT_CONFIG.cache.claim_timeout_seconds if timeout is None else timeout
    lock_path = claim_lock_path(path)
    lock = FileLock(lock_path, timeout=timeout)
    try:
        lock_path.parent.mkdir(parents=True, exist_ok=True)
        lock.acquire()
    except Timeout:  # before OSError, of which it is a subclass
        warnings.warn(f"{path}: another process has been computing it for over {timeout:g} s "
                      f"(lock {lock_path}); computing it here as well", ClaimWarning, stacklevel=3)
        yield False
        return
    except OSError:  # a read-only or full cache: nothing can be shared; the artefact's own write says why
        yield False
        return
    try:
        yield True
    finally:
        lock.release()


def compute_once(path: str | Path, load: Callable[[], Any], compute: Callable[[], Any],
                 timeout: float | None = None) -> Any:
    """``load()`` the artefact at ``path``, or ``compute()`` it under its claim.

    Parameters
    ----------
    path : str or Path
        Where ``compute`` writes the artefact (atomically).
    load : callable
        Returns the artefact, or None when it is missing or unreadable.
    compute : callable
        Makes, writes and returns it.
    timeout : float, optional
        See :func:`claim`.

    Returns
    -------
    What ``load`` or ``compute`` returned: with several processes on one cache, one computes
    and the others load its result once it is written.
    """
    found = load()
    if found is not None:
        return found
    with claim(path, timeout):
        found = load()  # another process may have written it while this one waited
        return found if found is not None else compute()


def content_key(*parts: Any) -> str:
    """SHA-256 hex digest of JSON-serialisable parts (strings, numbers, dicts, lists)."""
    digest = hashlib.sha256()
    for part in parts:
        digest.update(json.dumps(part, sort_keys=True, default=str).encode())
        digest.update(b"\0")
    return digest.hexdigest()


def source_fingerprint(*modules: ModuleType) -> str:
    """SHA-256 hex digest of the modules' source files.

    For the keys of cached measurements of code (timings, counts): editing a kernel
    measures again, and going back to the same source reuses the earlier result.
    """
    digest = hashlib.sha256()
    for module in modules:
        digest.update(Path(module.__file__).read_bytes())
        digest.update(b"\0")
    return digest.hexdigest()


def drop_stale_kernel_cache(kernels: ModuleType, *inlined_from: ModuleType) -> bool:
    """Delete numba's cached machine code of ``kernels`` if a module it inlines from has changed.

    numba decides whether a cached function is stale by its own source file only, so a
    kernel keeps running the old code of an edited function it inlines from another
    module (measured: renders timed after an edit of the packet traversal ran the code
    before it). Each kernel module therefore keeps a stamp, the
    :func:`source_fingerprint` of itself and ``inlined_from``, beside numba's cache files;
    when it differs, the module's cache files are deleted and numba compiles afresh. Call
    it before any kernel of the module runs. Returns True when it deleted the cache.
    """
    dispatcher = next((value for value in vars(kernels).values()
                       if getattr(getattr(value, "py_func", None), "__module__", None) == kernels.__name__
                       and hasattr(getattr(value, "_cache", None), "_cache_path")), None)
    if dispatcher is None:  # no cached kernel (or a numba without the attribute): nothing to guard
        return False
    folder = Path(dispatcher._cache._cache_path)
    name = kernels.__name__.rsplit(".", 1)[-1]
    stamp = folder / f"{name}.sources"
    fingerprint = source_fingerprint(kernels, *inlined_from)
    try:
        if stamp.read_text() == fingerprint:
            return False
    except OSError:
        pass
    stale = [path for path in folder.glob(f"{name}.*") if path.suffix in (".nbi", ".nbc")]
    for path in stale:
        path.unlink(missing_ok=True)
    try:
        atomic_write_bytes(stamp, fingerprint.encode())
    except OSError:  # a read-only install: numba cannot cache there either
        pass
    return bool(stale)


#: errno values of a write that ran out of room: the disk is full, or the user's quota is spent.
DISK_FULL_ERRNOS = (errno.ENOSPC, errno.EDQUOT)


def _megabytes(count: int) -> str:
    """``count`` bytes as ``"12.3 MB (12,345,678 bytes)"``."""
    return f"{count / 1e6:.1f} MB ({count:,} bytes)"


class DiskFullError(OSError):
    """A write ran out of disk space or quota; the destination was left as it was.

    Parameters
    ----------
    code : int
        ``errno.ENOSPC`` or ``errno.EDQUOT``.
    path : str or Path
        The file that was being written.
    bytes_needed : int or None
        Size of the complete file in bytes, when known before writing.
    bytes_free : int or None
        Free bytes on the destination's file system after the failure
        (``shutil.disk_usage``), None when that cannot be read.
    bytes_written : int
        Bytes of the temporary file when the write failed (deleted since).
    """

    def __init__(self, code: int, path: str | Path, bytes_needed: int | None, bytes_free: int | None,
                 bytes_written: int = 0) -> None:
        super().__init__(code, os.strerror(code), str(path))
        self.bytes_needed = bytes_needed
        self.bytes_free = bytes_free
        self.bytes_written = bytes_written

    def __reduce__(self):  # OSError's pickles only (errno, strerror): keep every field across processes
        return type(self), (self.errno, self.filename, self.bytes_needed, self.bytes_free, self.bytes_written)

    def __str__(self) -> str:
        if self.bytes_needed is not None:
            needed = f"needs {_megabytes(self.bytes_needed)}"
        else:
            needed = f"needs more than the {_megabytes(self.bytes_written)} written before the failure"
        free = "free space unknown" if self.bytes_free is None else f"{_megabytes(self.bytes_free)} free"
        return (f"cannot write {self.filename}: {self.strerror} ({needed}, {free}); "
                "the previous file, if any, is kept and no partial file was left")


def _free_bytes(folder: Path) -> int | None:
    """Free bytes on ``folder``'s file system for this user; None when it cannot be read."""
    try:
        return shutil.disk_usage(folder).free
    except OSError:
        return None


def atomic_write(path: str | Path, write: Callable[[str], None], size: int | None = None) -> Path:
    """Call ``write(temporary_path)`` beside ``path`` (same suffix), then rename it into place.

    The temporary file lives in the destination folder, so the rename is atomic: readers
    see the old file or the complete new one, never a partial write. Files are made
    world-readable (0644), since results and caches are meant to be shared.

    Parameters
    ----------
    path : str or Path
        Destination file.
    write : callable
        Writes the complete file to the path it is given.
    size : int, optional
        Bytes the file will take, when known, for the message of a full disk.

    Raises
    ------
    DiskFullError
        The disk or quota filled up (``ENOSPC``, ``EDQUOT``) while the temporary was made,
        written or renamed: it is deleted, ``path`` is unchanged, and the message names
        ``path``, ``size`` and the free bytes.
    OSError
        Any other failure, after the temporary is deleted.
    """
    path = Path(path)
    temporary = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
        os.close(handle)
        write(temporary)
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    except BaseException as error:
        written = 0
        if temporary is not None:
            with contextlib.suppress(OSError):
                written = os.stat(temporary).st_size
            Path(temporary).unlink(missing_ok=True)
        if isinstance(error, OSError) and error.errno in DISK_FULL_ERRNOS and not isinstance(error, DiskFullError):
            folder = next((parent for parent in (path.parent, *path.parents) if parent.is_dir()), Path("."))
            raise DiskFullError(error.errno, path, size, _free_bytes(folder), written) from error
        raise
    return path


def _write_all(path: str, data: bytes) -> None:
    """Write ``data`` to the existing file ``path`` with ``os.write`` until all of it is written."""
    handle = os.open(path, os.O_WRONLY | os.O_TRUNC)
    try:
        view = memoryview(data)
        while view:
            view = view[os.write(handle, view):]
    finally:
        os.close(handle)


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_write`; a full disk is a :class:`DiskFullError`)."""
    return atomic_write(path, lambda temporary: _write_all(temporary, data), size=len(data))


def npz_bytes(arrays: dict[str, np.ndarray]) -> int:
    """Upper bound of the bytes of an uncompressed ``.npz`` of ``arrays``: their data plus 1 KiB per array of headers."""
    return sum(np.asarray(array).nbytes + 1024 for array in arrays.values())


def save_npz(path: Path, arrays: dict[str, np.ndarray], metadata: dict[str, Any]) -> None:
    """Atomically save arrays plus a JSON metadata record to ``path`` (suffix ``.npz``).

    A full disk is a :class:`DiskFullError` naming ``path`` and :func:`npz_bytes`.
    """
    encoded = np.frombuffer(json.dumps(metadata).encode(), np.uint8)
    atomic_write(path, lambda temporary: np.savez(temporary, __metadata__=encoded, **arrays),
                 size=npz_bytes({"__metadata__": encoded, **arrays}))


def load_npz(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """Load what :func:`save_npz` wrote; None when missing or unreadable (a cache miss)."""
    try:
        with np.load(path) as data:
            arrays = {name: data[name] for name in data.files if name != "__metadata__"}
            metadata = json.loads(data["__metadata__"].tobytes().decode())
    except (OSError, ValueError, KeyError, EOFError):
        return None
    return arrays, metadata
