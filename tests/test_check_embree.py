"""`kdtrace check-embree` on the real scenes: zero unexplained disagreements.

The small scenes get 20,000 rays of each kind; the large ones a sample of 2,000 rays
of each kind (the full 1M-ray check is `kdtrace check-embree SCENE`, and runs in the
`slow` tier below).
"""

from __future__ import annotations

import warnings

import pytest

from kdtrace.kdtree import VARIANTS, build_kdtree
from kdtrace.scenes import load_scene
from references.agreement import AGREE, UNEXPLAINED, check_scene

SMALL = ["cbox-original", "cbox-mirror", "cbox-sphere", "cbox-empty", "car"]
LARGE = ["bunny", "dabrovic-sponza", "samurai-monastery", "crytek-sponza"]
SEED = 7


def run_check(name: str, rays_per_kind: int):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = load_scene(name)
        trees = {variant: build_kdtree(scene, variant) for variant in VARIANTS}
    return check_scene(scene, trees, rays_per_kind, SEED, progress=False)


@pytest.mark.parametrize("name", SMALL + LARGE)
def test_no_unexplained_disagreement_with_embree(shared_scenes, name):
    rays = 20_000 if name in SMALL else 2_000
    table = run_check(name, rays)
    assert set(table["kind"]) == {"primary", "random", "vertex", "edge", "shadow"}
    assert (table["rays"] == rays).all()
    assert table[UNEXPLAINED].sum() == 0, f"\n{table.to_string()}"
    assert table[AGREE].sum() > 0.8 * table["rays"].sum()  # most rays agree outright


@pytest.mark.slow
@pytest.mark.parametrize("name", SMALL + LARGE)
def test_no_unexplained_disagreement_with_embree_1m(shared_scenes, name):
    table = run_check(name, 1_000_000)
    assert table[UNEXPLAINED].sum() == 0, f"\n{table.to_string()}"


def test_cli_check_embree_prints_the_table_and_exit_status(shared_scenes, capsys):
    from kdtrace.cli import main

    assert main(["check-embree", "cbox-original", "--rays", "2000"]) == 0
    out = capsys.readouterr().out
    assert "| intersector" in out and "unexplained disagreements: 0" in out
    assert main(["check-embree", "no-such-scene"]) == 2
    assert "available:" in capsys.readouterr().err
