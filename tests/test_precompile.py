"""The ahead-of-use compilation of the ray-query kernels (kdtrace/precompile.py)."""

from __future__ import annotations

from kdtrace import precompile


def test_a_cold_cache_is_recognised_and_compiling_warms_it(tmp_path):
    assert precompile.cache_is_cold(tmp_path)
    for pattern in precompile.INDEX_GLOBS[:-1]:
        (tmp_path / pattern.replace("*", "10")).touch()
    assert precompile.cache_is_cold(tmp_path)  # one kind of query still missing
    (tmp_path / precompile.INDEX_GLOBS[-1].replace("*", "65")).touch()
    assert not precompile.cache_is_cold(tmp_path)
    precompile.compile_query_kernels()
    assert not precompile.cache_is_cold()
