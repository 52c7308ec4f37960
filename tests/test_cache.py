"""The content-addressed cache's keys and atomic writes."""

import importlib.util
import subprocess
import sys

import pytest

from kdtrace.cache import atomic_write, atomic_write_bytes, content_key, source_fingerprint


def _module_from(path, name):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_source_fingerprint_follows_the_source_not_the_file(tmp_path):
    path = tmp_path / "kernel_a.py"
    path.write_text("X = 1\n")
    module = _module_from(path, "kernel_a")
    before = source_fingerprint(module)
    path.write_text("X = 2\n")
    edited = source_fingerprint(module)
    path.write_text("X = 1\n")
    assert edited != before
    assert source_fingerprint(module) == before  # reverting the edit reuses the old key
    assert source_fingerprint(module, sys.modules[__name__]) != before


def test_content_key_depends_on_order_and_value():
    assert content_key("a", 1) != content_key(1, "a")
    assert content_key({"x": 1, "y": 2}) == content_key({"y": 2, "x": 1})
    assert content_key("a", 1) != content_key("a", 2)


def test_atomic_write_leaves_the_old_file_on_failure(tmp_path):
    target = tmp_path / "result.json"
    atomic_write_bytes(target, b"old")

    class Interrupted(Exception):
        pass


    def failing(temporary):
        with open(temporary, "wb") as handle:
            handle.write(b"half")
        raise Interrupted

    with pytest.raises(Interrupted):
        atomic_write(target, failing)
    assert target.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["result.json"]


KERNEL = '''
import sys
from numba import njit
import dep
from kdtrace.cache import drop_stale_kernel_cache

@njit(cache=True)
def kernel():
    return dep.value() + 0

if GUARD:
    drop_stale_kernel_cache(sys.modules[__name__], dep)
'''


def _run_kernel(folder) -> int:
    code = f"import sys; sys.path.insert(0, {str(folder)!r}); import kern; print(kern.kernel())"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120)
    return int(done.stdout.split()[-1])


@pytest.mark.parametrize("guard", [False, True])
def test_kernel_cache_follows_the_modules_it_inlines_from(tmp_path, guard):
    (tmp_path / "kern.py").write_text(KERNEL.replace("GUARD", str(guard)))
    (tmp_path / "dep.py").write_text("from numba import njit\n\n@njit(inline='always')\ndef value():\n    return 1\n")
    assert _run_kernel(tmp_path) == 1
    (tmp_path / "dep.py").write_text("from numba import njit\n\n@njit(inline='always')\ndef value():\n    return 2\n")
    # numba alone keeps the cached machine code of the unchanged kern.py (the hazard the guard removes).
    assert _run_kernel(tmp_path) == (2 if guard else 1)
    assert _run_kernel(tmp_path) == (2 if guard else 1)
