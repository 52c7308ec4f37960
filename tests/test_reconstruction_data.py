"""Precision Graphics datasets and superresolution pairs (reconstruction/data.py), quick profile."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

import kdtrace.cache
from kdtrace.config import DEFAULT_CONFIG, load_config
from kdtrace.imageio import srgb_decode
from kdtrace.scenes import load_scene
from reconstruction import data

QUICK = DEFAULT_CONFIG.reconstruction.profile("quick")
SCENE = "cbox-original"


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """The quick dataset of the Cornell box in a module-wide cache, with the number of views rendered."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("KDTRACE_CACHE", str(tmp_path_factory.mktemp("cache")))
        rendered = []
        original = data._render_view
        patch.setattr(data, "_render_view", lambda *args: rendered.append(args[1].name) or original(*args))
        yield data.generate_dataset(SCENE, QUICK, progress=False), rendered


def _dot_files(root):
    return [path.name for path in root.iterdir() if path.name.startswith(".")]


def test_generation_writes_every_view_and_a_manifest(dataset):
    dataset, rendered = dataset
    manifest = json.loads((dataset.root / "manifest.json").read_text())
    assert manifest == dataset.manifest
    candidates = QUICK.positions * QUICK.views_per_position
    assert len(rendered) == candidates and len(manifest["views"]) == candidates
    assert sorted(path.stem for path in dataset.root.glob("view-*.npz")) == sorted(rendered)
    assert manifest["scene_hash"] == load_scene(SCENE).content_hash()
    assert manifest["settings"]["spp"] == QUICK.spp and manifest["settings"]["reference"] == "mitsuba"
    assert {"machine", "versions", "config"} <= set(manifest["provenance"])
    assert dataset.root.name.endswith(dataset.key[:24])
    accepted = [view for view in manifest["views"] if view["accepted"]]
    assert len(accepted) >= 3
    for record in manifest["views"]:
        assert (record["coverage"] >= QUICK.min_coverage) == record["accepted"]
        assert record["noisy_seed"] != record["reference_seed"]
    view = dataset.load_view(accepted[0]["name"])
    for name, channels in data.BUFFERS.items():
        assert view[name].shape == (QUICK.height, QUICK.width, channels) and view[name].dtype == np.float32
        assert np.all(np.isfinite(view[name]))
    # the reference is far less noisy than the 4 spp input
    assert view["reference"].std() < view["noisy"].std()
    assert not _dot_files(dataset.root)


def test_candidate_views_turn_in_yaw_steps_inside_the_region():
    scene = load_scene(SCENE)
    views = data.candidate_views(scene, QUICK)
    lower, upper = data.movement_region(scene, QUICK.region_fraction)
    assert [view.yaw_degrees for view in views[: QUICK.views_per_position]] == [0.0, 22.5, -22.5, 45.0]
    for view in views:
        position = np.array(view.camera.position)
        assert np.all(position >= lower) and np.all(position <= upper)
        forward = np.subtract(view.camera.look_at, position)
        default = np.subtract(scene.camera.look_at, scene.camera.position)
        cosine = forward @ default / np.linalg.norm(forward) / np.linalg.norm(default)
        assert np.degrees(np.arccos(np.clip(cosine, -1, 1))) == pytest.approx(abs(view.yaw_degrees), abs=1e-6)
    assert [v.camera for v in views] == [v.camera for v in data.candidate_views(scene, QUICK)]


def test_rerun_is_a_cache_hit_and_a_lost_manifest_renders_nothing(dataset, monkeypatch):
    dataset, _ = dataset
    monkeypatch.setenv("KDTRACE_CACHE", str(dataset.root.parent.parent))
    calls = []
    monkeypatch.setattr(data, "_render_view", lambda *args: calls.append(args) or pytest.fail("rendered"))
    assert data.generate_dataset(SCENE, QUICK, progress=False).manifest == dataset.manifest
    manifest = (dataset.root / "manifest.json").read_bytes()
    (dataset.root / "manifest.json").unlink()
    again = data.generate_dataset(SCENE, QUICK, progress=False)
    (dataset.root / "manifest.json").write_bytes(manifest)
    assert not calls and again.manifest["splits"] == dataset.manifest["splits"]
    assert again.manifest["views"] == dataset.manifest["views"]
    # another setting is another dataset
    other = dataclasses.replace(QUICK, spp=8)
    assert data.dataset_key(load_scene(SCENE), other) != dataset.key


def test_interrupted_generation_resumes_without_partial_files(dataset, tmp_path, monkeypatch):
    dataset, _ = dataset
    monkeypatch.setenv("KDTRACE_CACHE", str(tmp_path / "cache"))
    original_render, original_savez = data._render_view, np.savez
    rendered = []

    def render_three(*args):
        rendered.append(args[1].name)
        return original_render(*args)

    def savez_then_die(file, *args, **kwargs):
        if len(rendered) == 3:  # the third view dies half-way through its write
            with open(file, "wb") as handle:
                handle.write(b"PK\x03\x04 half a file")
            raise KeyboardInterrupt
        return original_savez(file, *args, **kwargs)

    monkeypatch.setattr(data, "_render_view", render_three)
    monkeypatch.setattr(kdtrace.cache.np, "savez", savez_then_die)
    with pytest.raises(KeyboardInterrupt):
        data.generate_dataset(SCENE, QUICK, progress=False)
    root = data.dataset_dir(load_scene(SCENE), QUICK)
    assert sorted(path.name for path in root.iterdir()) == ["view-0000.npz", "view-0001.npz"]
    monkeypatch.setattr(kdtrace.cache.np, "savez", original_savez)
    rendered.clear()
    resumed = data.generate_dataset(SCENE, QUICK, progress=False)
    assert rendered == [f"view-{i:04d}" for i in range(2, QUICK.positions * QUICK.views_per_position)]
    assert not _dot_files(root)
    assert resumed.manifest["splits"] == dataset.manifest["splits"]
    for name in dataset.views():
        first, second = dataset.load_view(name), resumed.load_view(name)
        for buffer in data.BUFFERS:
            np.testing.assert_array_equal(first[buffer], second[buffer])


def test_split_is_by_view_and_crops_come_from_their_split(dataset):
    dataset, _ = dataset
    splits = {split: set(dataset.views(split)) for split in data.SPLITS}
    assert all(splits.values())
    assert not (splits["train"] & splits["validation"] or splits["train"] & splits["test"]
                or splits["validation"] & splits["test"])
    accepted = {view["name"] for view in dataset.manifest["views"] if view["accepted"]}
    assert set().union(*splits.values()) == accepted
    for split in data.SPLITS:
        crops = data.crops(dataset, split, QUICK.crop_size, QUICK.crops_per_view, QUICK.seed)
        count = len(splits[split]) * QUICK.crops_per_view
        assert crops["noisy"].shape == (count, 3, QUICK.crop_size, QUICK.crop_size)
        assert crops["depth"].shape == (count, 1, QUICK.crop_size, QUICK.crop_size)
        # every crop is a window of one of the split's own views
        views = [dataset.load_view(name)["reference"] for name in sorted(splits[split])]
        for crop in crops["reference"][:: QUICK.crops_per_view]:
            window = crop.transpose(1, 2, 0)
            assert any(_contains(view, window) for view in views)
    again = data.crops(dataset, "train", QUICK.crop_size, QUICK.crops_per_view, QUICK.seed)
    np.testing.assert_array_equal(again["noisy"], data.crops(dataset, "train", QUICK.crop_size,
                                                             QUICK.crops_per_view, QUICK.seed)["noisy"])
    with pytest.raises(ValueError, match="exceeds"):
        data.crops(dataset, "train", QUICK.width + 1, 1, 0)
    with pytest.raises(ValueError, match="unknown split"):
        dataset.views("everything")


def _contains(image, window):
    size = window.shape[0]
    return any(np.array_equal(image[top:top + size, left:left + size], window)
               for top in range(image.shape[0] - size + 1) for left in range(image.shape[1] - size + 1))


def test_too_few_accepted_views_is_a_clear_error():
    with pytest.raises(ValueError, match="at least 3"):
        data.split_views(["view-0000", "view-0001"], QUICK)


def _sharpness(images):
    """Mean squared discrete Laplacian of (N, C, H, W) images (interior pixels)."""
    laplacian = (images[..., 1:-1, :-2] + images[..., 1:-1, 2:] + images[..., :-2, 1:-1] + images[..., 2:, 1:-1]
                 - 4 * images[..., 1:-1, 1:-1])
    return float(np.mean(laplacian ** 2))


def test_superres_pairs_have_matching_shapes_and_blurrier_inputs(dataset):
    dataset, _ = dataset
    pairs = data.superres_data(QUICK, [dataset])
    size = QUICK.superres_crop_size
    photos = (len(data.TRAIN_PHOTOS), len(data.VALIDATION_PHOTOS), 0)
    for split, extra in zip(data.SPLITS, photos, strict=True):
        count = (extra + len(dataset.views(split))) * QUICK.superres_crops_per_image
        assert pairs[split]["input"].shape == pairs[split]["target"].shape == (count, 3, size, size)
        assert pairs[split]["input"].dtype == np.float32
        assert 0.0 <= pairs[split]["target"].min() and pairs[split]["target"].max() <= 1.0
        assert _sharpness(pairs[split]["input"]) < 0.7 * _sharpness(pairs[split]["target"])
    assert "test" not in data.superres_data(QUICK)


def test_degrade_keeps_smooth_images_and_blurs_fine_detail():
    ramp = np.broadcast_to(np.linspace(0.2, 0.8, 16, dtype=np.float32), (1, 1, 16, 16)).copy()
    for method in ("area", "bicubic"):
        np.testing.assert_allclose(data.degrade(ramp, method)[..., 3:-3, 3:-3], ramp[..., 3:-3, 3:-3], atol=0.02)
    checker = (np.indices((16, 16)).sum(0) % 2).astype(np.float32)[None, None]
    np.testing.assert_allclose(data.degrade(checker, "area"), 0.5, atol=1e-5)  # the box mean of a checkerboard
    with pytest.raises(ValueError, match="even"):
        data.degrade(np.zeros((1, 1, 5, 6), np.float32))


def test_photos_are_bundled_linear_rgb():
    for name in data.TRAIN_PHOTOS + data.VALIDATION_PHOTOS:
        image = data.photo(name)
        assert image.ndim == 3 and image.shape[2] == 3 and 0.0 <= image.min() and image.max() <= 1.0
    assert srgb_decode(np.float32(0.5)) == pytest.approx(0.21404, abs=1e-4)


def test_user_config_adds_and_overrides_reconstruction_profiles(tmp_path):
    path = tmp_path / "user.toml"
    path.write_text("[reconstruction.profiles.mine]\npositions = 3\n"
                    "[reconstruction.profiles.quick]\nepochs = 7\n")
    config = load_config(path)
    assert config.reconstruction.profile("mine").positions == 3
    assert config.reconstruction.profile("mine").views_per_position == 16  # the dataclass default
    assert config.reconstruction.profile("quick").epochs == 7
    assert config.reconstruction.profile("quick").width == QUICK.width
    path.write_text("[reconstruction.profiles.quick]\nepoch = 7\n")
    with pytest.raises(ValueError, match="unknown keys"):
        load_config(path)
    with pytest.raises(ValueError, match="unknown reconstruction profile"):
        DEFAULT_CONFIG.reconstruction.profile("nope")
    with pytest.raises(ValueError, match="reference"):
        dataclasses.replace(QUICK, reference="blender")


def test_an_unusable_mitsuba_variant_falls_back_with_a_warning():
    assert data.reference_variant(None) is None and data.reference_variant("") is None
    assert data.reference_variant("scalar_rgb") == "scalar_rgb"
    # no GPU variant is supported by references.mitsuba yet, and this machine has no GPU either way
    with pytest.warns(UserWarning, match="cuda_ad_rgb"):
        assert data.reference_variant("cuda_ad_rgb") is None


def test_augmented_superres_photos_are_flipped_rotated_and_exposed_training_crops_only():
    augmented = dataclasses.replace(QUICK, superres_augment=True)
    plain, more = data.superres_data(QUICK), data.superres_data(augmented)
    assert len(more["train"]["target"]) == data.AUGMENT_FACTOR * len(plain["train"]["target"])
    np.testing.assert_array_equal(more["validation"]["target"], plain["validation"]["target"])
    assert 0.0 <= more["train"]["target"].min() and more["train"]["target"].max() <= 1.0
    rng = np.random.default_rng(0)
    crop = np.random.default_rng(1).uniform(0.2, 0.4, (3, 8, 8))
    outputs = [data.augment(crop, rng) for _ in range(64)]
    # every output is one of the 8 symmetries of the crop times one exposure
    for output in outputs:
        scale = output.mean() / crop.mean()
        assert data.AUGMENT_EXPOSURE[0] <= scale <= data.AUGMENT_EXPOSURE[1]
        symmetries = [np.rot90(c, k, axes=(1, 2)) for c in (crop, crop[:, :, ::-1]) for k in range(4)]
        assert min(np.abs(output / scale - s).max() for s in symmetries) < 1e-9
    assert len({np.round(o / (o.mean() / crop.mean()), 9).tobytes() for o in outputs}) == 8


def test_a_dataset_too_large_for_the_disk_is_refused_before_rendering(tmp_path, monkeypatch):
    monkeypatch.setenv("KDTRACE_CACHE", str(tmp_path))
    big = dataclasses.replace(QUICK, width=4096, height=4096)
    free = 10 * data.view_bytes(big)  # room for 10 views, the profile has 16 candidates
    monkeypatch.setattr(data.shutil, "disk_usage", lambda path: type("Usage", (), {"free": free})())
    with pytest.raises(data.DatasetWriteError, match=r"needs up to .* GB for 16 more views of 4096x4096"):
        data.generate_dataset(SCENE, big, progress=False)
    from kdtrace.scenes import load_scene

    assert not list(data.dataset_dir(load_scene(SCENE), big).glob("view-*"))  # nothing was rendered


def test_display_superres_pairs_are_the_displayed_crops_and_their_displayed_half_size_images(dataset):
    from reconstruction.metrics import display_exposures, to_display

    dataset, _ = dataset
    linear, shown = data.superres_data(QUICK, [dataset]), data.superres_data(QUICK, [dataset], "display")
    test_views = [np.clip(dataset.load_view(name)["reference"], 0, 1) for name in dataset.views("test")]
    exposures = display_exposures(test_views)[1]
    count = QUICK.superres_crops_per_image
    for index, exposure in enumerate(exposures):  # the test split is renders only, each view's crops in turn
        crops = slice(index * count, (index + 1) * count)
        target = linear["test"]["target"][crops]
        np.testing.assert_allclose(shown["test"]["target"][crops], to_display(target, exposure), atol=1e-6)
        inputs, _ = data.degrade_displayed(target, [exposure] * count, QUICK.superres_downsample)
        np.testing.assert_array_equal(shown["test"]["input"][crops], inputs)
    # reduced in linear radiance, then shown: a checkerboard's half-size image is its displayed mean,
    # not the mean of its displayed values
    checker = (np.indices((8, 8)).sum(0) % 2).astype(np.float32)[None, None].repeat(3, axis=1)
    inputs, targets = data.degrade_displayed(checker, [1.0])
    np.testing.assert_allclose(inputs, to_display(np.float32(0.5), 1.0), atol=1e-5)
    np.testing.assert_array_equal(targets, checker)
    with pytest.raises(ValueError, match="2 exposures for 1 crops"):
        data.degrade_displayed(checker, [1.0, 1.0])
    with pytest.raises(ValueError, match="unknown superresolution space"):
        data.superres_data(QUICK, [], "log")
