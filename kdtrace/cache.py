"""Content-addressed on-disk cache with atomic writes.

Artefacts (KD-trees now; references and models later) are stored as ``.npz`` files
named by a SHA-256 key of everything they depend on. Writes go to a temporary file in
the same directory and are renamed into place, so an interrupted run never leaves a
half-written artefact behind.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from kdtrace.config import DEFAULT_CONFIG


def cache_root() -> Path:
    """The cache directory: ``$KDTRACE_CACHE`` or the configured default."""
    return Path(os.environ.get("KDTRACE_CACHE", DEFAULT_CONFIG.cache.directory))


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


def atomic_write(path: str | Path, write: Callable[[str], None]) -> Path:
    """Call ``write(temporary_path)`` beside ``path`` (same suffix), then rename it into place.

    The temporary file lives in the destination folder, so the rename is atomic: readers
    see the old file or the complete new one, never a partial write. Files are made
    world-readable (0644), since results and caches are meant to be shared.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    os.close(handle)
    try:
        write(temporary)
        os.chmod(temporary, 0o644)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (see :func:`atomic_write`)."""
    return atomic_write(path, lambda temporary: Path(temporary).write_bytes(data))


def save_npz(path: Path, arrays: dict[str, np.ndarray], metadata: dict[str, Any]) -> None:
    """Atomically save arrays plus a JSON metadata record to ``path`` (suffix ``.npz``)."""
    encoded = np.frombuffer(json.dumps(metadata).encode(), np.uint8)
    atomic_write(path, lambda temporary: np.savez(temporary, __metadata__=encoded, **arrays))


def load_npz(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """Load what :func:`save_npz` wrote; None when missing or unreadable (a cache miss)."""
    try:
        with np.load(path) as data:
            arrays = {name: data[name] for name in data.files if name != "__metadata__"}
            metadata = json.loads(data["__metadata__"].tobytes().decode())
    except (OSError, ValueError, KeyError, EOFError):
        return None
    return arrays, metadata
