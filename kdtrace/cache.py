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
from pathlib import Path
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


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as stream:
            stream.write(data)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def save_npz(path: Path, arrays: dict[str, np.ndarray], metadata: dict[str, Any]) -> None:
    """Atomically save arrays plus a JSON metadata record to ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp.npz")
    os.close(handle)
    try:
        np.savez(temporary, __metadata__=np.frombuffer(json.dumps(metadata).encode(), np.uint8), **arrays)
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def load_npz(path: Path) -> tuple[dict[str, np.ndarray], dict[str, Any]] | None:
    """Load what :func:`save_npz` wrote; None when missing or unreadable (a cache miss)."""
    try:
        with np.load(path) as data:
            arrays = {name: data[name] for name in data.files if name != "__metadata__"}
            metadata = json.loads(data["__metadata__"].tobytes().decode())
    except (OSError, ValueError, KeyError, EOFError):
        return None
    return arrays, metadata
