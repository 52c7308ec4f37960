"""Table 1 under the paper's build recipe and ours (reports/sensitivity.py), on a small scene."""

from __future__ import annotations

import dataclasses
import json

from kdtrace.config import DEFAULT_CONFIG
from reports import sensitivity


def _config():
    tiny = dataclasses.replace(DEFAULT_CONFIG.profile("quick"), scenes=("cbox-sphere", "cbox-original"),
                               sensitivity_scenes=("cbox-sphere", "car"), timing_rays=2000,
                               frame_width=16, frame_height=16, frame_spp=1)
    return dataclasses.replace(DEFAULT_CONFIG, profiles={"tiny": tiny})


def test_paper_recipe_is_the_papers_build():
    paper = sensitivity.recipes(DEFAULT_CONFIG)["paper"]
    assert (paper.axis_selection, paper.split_candidates, paper.empty_bonus) == ("cycle", "centroids", 0.0)
    assert sensitivity.recipes(DEFAULT_CONFIG)["ours"] == DEFAULT_CONFIG.kdtree


def test_rows_tables_metrics_and_reuse(tmp_path):
    config = _config()
    rows, reused = sensitivity.generate(config, "tiny", tmp_path, progress=False)
    # only the sensitivity scenes that the profile renders
    assert [row["scene"] for row in rows] == ["cbox-sphere"] and reused == []
    row = rows[0]
    for recipe in sensitivity.RECIPES:
        # the pull-up only moves references up: never more than the naive tree's
        assert row[f"{recipe}_local_references"] <= row[f"{recipe}_naive_references"]
        assert 0.0 <= row[f"{recipe}_reduction"] < 1.0
        for kind in ("primary", "incoherent"):
            assert row[f"{recipe}_{kind}_local_over_naive"] > 0
            assert row[f"{recipe}_{kind}_nodes_per_ray_local"] > 0
    # different recipes build different trees
    assert (row["paper_naive_references"], row["paper_naive_nodes"]) != (row["ours_naive_references"], row["ours_naive_nodes"])
    text = (tmp_path / "table1_sensitivity.md").read_text()
    assert "| cbox-sphere | paper" in text and "| cbox-sphere | ours" in text
    assert json.loads((tmp_path / "rows" / "sensitivity" / "cbox-sphere.json").read_text())["row"] == row
    again, reused = sensitivity.generate(config, "tiny", tmp_path, progress=False)
    assert again == rows and len(reused) == 1
    names = {m.name for m in sensitivity.metrics_of(rows)}
    assert "table1_sensitivity/cbox-sphere/paper/triangle_references_local" in names
    assert "table1_sensitivity/cbox-sphere/ours/local_over_naive_incoherent" in names
