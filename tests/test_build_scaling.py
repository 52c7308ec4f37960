"""Unit tests of the KD-tree build-scaling part of Table 1 (reports/build_scaling.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from kdtrace.config import DEFAULT_CONFIG
from kdtrace.scene import Material, Scene
from reports import build_scaling


def soup(n: int, seed: int = 5) -> Scene:
    rng = np.random.default_rng(seed)
    vertices = (rng.uniform(-1, 1, (n, 1, 3)) + rng.normal(0, 0.05, (n, 3, 3))).reshape(-1, 3).astype(np.float32)
    return Scene("soup", vertices, np.arange(3 * n).reshape(n, 3), np.zeros(n, np.int32), [Material("grey")])


def test_subsets_are_nested_and_sized():
    scene = soup(1000)
    small, large = build_scaling.triangle_subset(scene, 100), build_scaling.triangle_subset(scene, 400)
    assert len(small.triangles) == 100 and len(large.triangles) == 400
    as_set = {tuple(t) for t in large.triangles.tolist()}
    assert all(tuple(t) in as_set for t in small.triangles.tolist())
    with pytest.raises(ValueError, match="out of range"):
        build_scaling.triangle_subset(scene, 1001)


def test_loglog_slope_recovers_a_power_law():
    n = np.array([1e3, 2e3, 4e3, 8e3])
    assert build_scaling.loglog_slope(n, 3e-6 * n**1.5) == pytest.approx(1.5)
    # N log N and N log^2 N are both steeper than linear over these sizes, and ordered.
    assert 1.0 < build_scaling.loglog_slope(n, n * np.log(n)) < build_scaling.loglog_slope(n, n * np.log(n) ** 2)


def test_generate_writes_table_and_figure_and_reuses(tmp_path, monkeypatch):
    scene = soup(4000)
    monkeypatch.setattr(build_scaling, "load_scene", lambda name: scene)
    record, reused = build_scaling.generate(DEFAULT_CONFIG, "soup", tmp_path)
    assert not reused
    counts = [row["triangles"] for row in record["rows"]]
    assert counts == [round(f * 4000) for f in build_scaling.FRACTIONS]
    for variant in ("naive", "local"):
        assert all(row[f"{variant}_seconds"] > 0 for row in record["rows"])
        assert np.isfinite(record["slopes"][variant])
    # The local tree is the naive one with the pull-up: never more references.
    assert all(row["local_references"] <= row["naive_references"] for row in record["rows"])
    text = (tmp_path / "table1_build.md").read_text()
    assert f"local {record['slopes']['local']:.2f}" in text and "figures/build_scaling.png" in text
    assert (tmp_path / "figures" / "build_scaling.png").stat().st_size > 1000
    assert json.loads((tmp_path / "rows" / "build_scaling.json").read_text())["key"] == record["key"]
    again, reused = build_scaling.generate(DEFAULT_CONFIG, "soup", tmp_path)
    assert reused and again["slopes"] == record["slopes"]
    names = {m.name for m in build_scaling.metrics_of(record)}
    assert names == {"table1/build_scaling/naive_slope", "table1/build_scaling/local_slope"}
