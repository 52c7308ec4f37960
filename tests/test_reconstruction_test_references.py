"""Refined test references (reconstruction/test_references.py) on a tiny Cornell-box dataset."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from kdtrace.config import DEFAULT_CONFIG, load_config
from kdtrace.scenes import load_scene
from reconstruction import data, test_references
from reports import error_time
from reports.reconstruction_tables import reference_noise

SCENE = "cbox-original"
#: 32x32 views, 16-spp references; the test views' refined to 64 spp.
TINY = dataclasses.replace(DEFAULT_CONFIG.reconstruction.profile("quick"), width=32, height=32, reference_spp=16,
                           test_reference_spp_by_scene={SCENE: 64})


@pytest.fixture(scope="module")
def refined(tmp_path_factory):
    """The tiny dataset and its refined version, in a module-wide cache."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("KDTRACE_CACHE", str(tmp_path_factory.mktemp("cache")))
        patch.delenv("KDTRACE_SCHEDULER", raising=False)
        dataset = data.generate_dataset(SCENE, TINY, progress=False)
        yield dataset, test_references.refine_test_references(dataset, load_scene(SCENE), TINY, progress=False)


def _render(record: dict, spp: int, seed: int) -> np.ndarray:
    from references.mitsuba import render_reference

    scene = dataclasses.replace(load_scene(SCENE), cameras=[data.view_camera(record)])
    with data._one_jit_thread():
        return render_reference(scene, spp=spp, max_depth=TINY.max_depth, seed=seed, width=TINY.width,
                                height=TINY.height, cache=False).rgb


def test_a_test_reference_is_the_sample_weighted_mean_with_an_independent_render(refined):
    dataset, better = refined
    assert better.key == dataset.key and better.reference_spp("test") == 64 and better.reference_spp("train") == 16
    records = {record["name"]: record for record in dataset.manifest["views"]}
    name = dataset.views("test")[0]
    record = records[name]
    seed = test_references.refinement_seed(record["reference_seed"], 64)
    assert seed not in (record["noisy_seed"], record["reference_seed"])
    # the oracle: the same extra samples rendered here, then the weighted mean written out
    expected = (16 * dataset.load_view(name)["reference"].astype(np.float64) + 48 * _render(record, 48, seed)) / 64
    np.testing.assert_allclose(better.load_view(name)["reference"], expected, rtol=1e-6, atol=1e-7)
    for buffer in ("noisy", "albedo", "normal", "depth"):
        assert better.load_view(name)[buffer].tobytes() == dataset.load_view(name)[buffer].tobytes()
    for other in dataset.views("train") + dataset.views("validation"):
        assert better.load_view(other)["reference"].tobytes() == dataset.load_view(other)["reference"].tobytes()


@pytest.mark.statistical
def test_refined_references_are_closer_to_a_converged_render(refined):
    dataset, better = refined
    records = {record["name"]: record for record in dataset.manifest["views"]}
    base_error = refined_error = 0.0
    for name in dataset.views("test"):
        converged = _render(records[name], 1024, 12345)
        base_error += float(np.mean((dataset.load_view(name)["reference"] - converged) ** 2))
        refined_error += float(np.mean((better.load_view(name)["reference"] - converged) ** 2))
    # 4x the samples: a quarter of the variance (plus the converged render's own, 1/64 of the base's)
    assert 0.15 < refined_error / base_error < 0.45
    # and the estimate of the references' own noise follows: about 10*log10(4) = 6 dB higher
    before = reference_noise(dataset, "test", TINY.spp, 16)
    after = reference_noise(better, "test", TINY.spp, better.reference_spp("test"))
    assert after["reference_spp"] == 64 and len(after["psnrs"]) == len(dataset.views("test"))
    assert 4.5 < after["pooled_psnr"] - before["pooled_psnr"] < 7.5


def test_refinement_resumes_renders_nothing_twice_and_rejects_foreign_files(refined, monkeypatch):
    dataset, better = refined
    scene = load_scene(SCENE)
    rendered = []
    original = test_references.refine_view
    monkeypatch.setattr(test_references, "refine_view", lambda *args: rendered.append(args[2]["name"]) or original(*args))
    monkeypatch.setattr("references.mitsuba.render_reference", lambda *a, **k: pytest.fail("rendered again"))
    assert test_references.refine_test_references(dataset, scene, TINY, progress=False) == better
    assert rendered == []
    # a lost view and a corrupt one are made again; the others are kept
    first, second = dataset.views("test")[:2]
    kept = {name: better.load_view(name)["reference"].tobytes() for name in dataset.views("test")}
    files = sorted(path.name for path in better.folder.iterdir())
    (better.folder / f"{first}.npz").unlink()
    (better.folder / f"{second}.npz").write_bytes(b"not an npz")
    monkeypatch.undo()
    monkeypatch.setattr(test_references, "refine_view", lambda *args: rendered.append(args[2]["name"]) or original(*args))
    test_references.refine_test_references(dataset, scene, TINY, progress=False)
    assert sorted(rendered) == sorted([first, second])
    assert {name: better.load_view(name)["reference"].tobytes() for name in dataset.views("test")} == kept  # reproducible
    assert sorted(path.name for path in better.folder.iterdir()) == files  # no temporaries left
    # a file of another refinement is refused by name
    foreign = dataclasses.replace(better, refinement_key="another")
    with pytest.raises(ValueError, match=f"{first}.npz is missing, corrupt or not a refined reference"):
        foreign.load_view(first)


def test_a_scene_that_does_not_need_it_renders_nothing(refined, monkeypatch):
    dataset, _ = refined
    monkeypatch.setattr(test_references, "refine_view", lambda *args: pytest.fail("rendered"))
    plain = dataclasses.replace(TINY, test_reference_spp_by_scene={})
    same = test_references.refine_test_references(dataset, load_scene(SCENE), plain, progress=False)
    assert same.folder is None and same.reference_spp("test") == 16
    name = dataset.views("test")[0]
    assert same.load_view(name)["reference"].tobytes() == dataset.load_view(name)["reference"].tobytes()
    other = dataclasses.replace(TINY, test_reference_spp_by_scene={SCENE: 64}, spp=2)  # another dataset
    with pytest.raises(ValueError, match="not cbox-original's dataset"):
        test_references.refine_test_references(dataset, load_scene(SCENE), other, progress=False)


def test_the_setting_is_checked_and_kept_out_of_the_sweeps_keys(tmp_path):
    with pytest.raises(ValueError, match="test_reference_spp_by_scene must be >= reference_spp"):
        dataclasses.replace(TINY, test_reference_spp_by_scene={SCENE: 8})
    with pytest.raises(ValueError, match="maps scene names to samples per pixel"):
        dataclasses.replace(TINY, test_reference_spp_by_scene={SCENE: 64.0})
    path = tmp_path / "config.toml"
    path.write_text("[reconstruction.profiles.tiny]\nreference_spp = 16\n"
                    "test_reference_spp_by_scene = { crytek-sponza = 96, car = 32 }\n")
    tiny = load_config(path).reconstruction.profile("tiny")
    assert tiny.test_reference_spp_by_scene == (("car", 32), ("crytek-sponza", 96))
    assert tiny.test_reference_spp("crytek-sponza") == 96 and tiny.test_reference_spp("pine") == 16
    # the sweep's and §6.4's rows have references of their own: their cached rows stay valid
    profile = DEFAULT_CONFIG.profile("standard")
    assert (error_time.row_settings(DEFAULT_CONFIG, profile, TINY)
            == error_time.row_settings(DEFAULT_CONFIG, profile, dataclasses.replace(TINY, test_reference_spp_by_scene={})))
    fields = {field.name for field in dataclasses.fields(TINY)}
    assert set(error_time.row_settings(DEFAULT_CONFIG, profile, TINY)[1]) == fields - {"test_reference_spp_by_scene"}
