"""The report's figure panels (reports/figures.py): files, sizes, crop rule, printed PSNRs, bad input.

Synthetic 32x32 images for the unit tests; one end-to-end test of ``scene_figures`` on the
cached ``quick`` cbox-original dataset (skipped when that dataset is not in the cache, so
the test never renders), with freshly seeded networks: the figures' plumbing does not
depend on how well the networks are trained, and a seeded net needs no training cache.
"""

from __future__ import annotations

import importlib.util
import math

import numpy as np
import pytest
import torch
from matplotlib.image import imread

from reconstruction.metrics import psnr, to_display
from reports import figures

SIDE = 32
HAVE_OIDN = importlib.util.find_spec("pyoidn") is not None


def _png_shape(path) -> tuple[int, int]:
    with open(path, "rb") as handle:
        assert handle.read(8) == b"\x89PNG\r\n\x1a\n"
    return imread(path).shape[:2]


@pytest.fixture
def scene_images():
    """A 32x32 reference with a textured square at rows 20-27, columns 4-11, and noisy versions."""
    rng = np.random.default_rng(7)
    reference = np.full((SIDE, SIDE, 3), 0.3, np.float32)
    reference[20:28, 4:12] = (np.indices((8, 8)).sum(axis=0) % 2)[:, :, None] * 0.8
    noisy = np.clip(reference + rng.normal(0.0, 0.1, reference.shape), 0.0, None).astype(np.float32)
    ours = (0.5 * noisy + 0.5 * reference).astype(np.float32)
    return {"noisy": noisy, "ours": ours, "reference": reference}


def test_display_is_the_srgb_curve_of_clipped_linear_values():
    from kdtrace.imageio import srgb_encode

    linear = np.array([[[-0.5, 0.0, 0.002], [0.18, 1.0, 4.0]]])
    assert np.allclose(figures.display(linear), srgb_encode(np.clip(linear, 0.0, 1.0)))
    assert figures.display(np.ones((2, 2))).shape == (2, 2, 3)


def test_non_finite_values_are_replaced_for_display_with_a_warning(scene_images, tmp_path):
    broken = scene_images["ours"].copy()
    broken[0, 0] = np.nan
    broken[0, 1] = np.inf
    with pytest.warns(RuntimeWarning, match="6 NaN/inf"):
        shown = figures.display(broken, "ours")
    assert np.all(np.isfinite(shown)) and shown[0, 0, 0] == 0.0 and shown[0, 1, 0] == pytest.approx(1.0)
    with pytest.warns(RuntimeWarning, match="NaN/inf"):
        panel = figures.denoising_panel({"noisy": scene_images["noisy"], "ours": broken},
                                        scene_images["reference"], tmp_path / "broken.png")
    assert math.isnan(panel.psnr["ours"]) and panel.labels["ours"] == "PSNR n/a (non-finite)"
    assert panel.psnr["noisy"] == psnr(scene_images["noisy"], scene_images["reference"])


def test_auto_crop_is_inside_the_image_on_the_reference_detail(scene_images):
    top, left, rows, columns = figures.auto_crop(scene_images["reference"])
    assert rows == columns == figures.MIN_CROP
    assert 0 <= top and top + rows <= SIDE and 0 <= left and left + columns <= SIDE
    assert (top, left) == (20, 4)  # the checkerboard holds all the detail
    wide = figures.auto_crop(np.zeros((40, 100, 3)))
    assert wide == (0, 0, 10, 10)  # flat: the first window; a quarter of the smaller side


def test_a_scaled_crop_stays_inside_and_is_never_empty():
    assert figures.scale_crop((20, 4, 8, 8), 0.5, (16, 16)) == (10, 2, 4, 4)
    assert figures.scale_crop((31, 31, 1, 1), 0.5, (16, 16)) == (15, 15, 1, 1)
    assert figures.scale_crop((3, 5, 3, 3), 0.5, (16, 16)) == (1, 2, 2, 2)


def test_denoising_panel_writes_a_png_with_the_metrics_psnrs(scene_images, tmp_path):
    reference = scene_images["reference"]
    images = {"noisy": scene_images["noisy"], "ours": scene_images["ours"], "mixed": scene_images["noisy"] * 0.9}
    panel = figures.denoising_panel(images, reference, tmp_path / "figures" / "denoising.png",
                                    title="synthetic", reference_label="reference, 64 spp")
    assert panel.path.is_file() and panel.path.stat().st_size < figures.MAX_PNG_BYTES
    columns = len(images) + 1
    height = round(2 * figures.PANEL_INCHES * figures.DPI + 0.3 * figures.DPI)
    assert _png_shape(panel.path) == (height, round(columns * figures.PANEL_INCHES * figures.DPI))
    assert list(panel.psnr) == list(images)
    exposure = figures.figure_exposure(reference)
    for name, image in images.items():
        assert panel.psnr[name] == psnr(image, reference)
        shown = psnr(to_display(image, exposure), to_display(reference, exposure))
        assert panel.labels[name] == f"display {shown:.2f} dB · linear {psnr(image, reference):.2f} dB"
    assert panel.crop == figures.auto_crop(reference)


def test_the_automatic_crop_does_not_depend_on_ours(scene_images, tmp_path):
    reference = scene_images["reference"]
    crops = []
    for index, ours in enumerate((scene_images["ours"], reference.copy(), np.zeros_like(reference))):
        panel = figures.denoising_panel({"noisy": scene_images["noisy"], "ours": ours}, reference, tmp_path / f"{index}.png")
        crops.append(panel.crop)
    assert crops[0] == crops[1] == crops[2] == figures.auto_crop(reference)
    assert math.isinf(figures.denoising_panel({"same": reference}, reference, tmp_path / "same.png").psnr["same"])


def test_a_given_crop_is_used_and_checked(scene_images, tmp_path):
    panel = figures.denoising_panel({"noisy": scene_images["noisy"]}, scene_images["reference"], tmp_path / "c.png",
                                    crop=(1, 2, 5, 6))
    assert panel.crop == (1, 2, 5, 6)
    for crop in ((30, 0, 4, 4), (0, 0, 0, 4), (-1, 0, 4, 4), (0, 0, 4)):
        with pytest.raises(ValueError, match="crop"):
            figures.denoising_panel({"noisy": scene_images["noisy"]}, scene_images["reference"], tmp_path / "c.png",
                                    crop=crop)


def test_superres_panel(scene_images, tmp_path):
    reference = scene_images["reference"]
    low = reference.reshape(SIDE // 2, 2, SIDE // 2, 2, 3).mean(axis=(1, 3))
    bicubic, ours = np.repeat(np.repeat(low, 2, 0), 2, 1), scene_images["ours"]
    panel = figures.superres_panel(low, bicubic, ours, reference, tmp_path / "sr.png")
    assert _png_shape(panel.path) == (round(2 * figures.PANEL_INCHES * figures.DPI),
                                      round(4 * figures.PANEL_INCHES * figures.DPI))
    assert panel.psnr == {"bicubic": psnr(bicubic, reference), "ours": psnr(ours, reference)}
    assert panel.crop == figures.auto_crop(reference)
    with pytest.raises(ValueError, match="half"):
        figures.superres_panel(reference, bicubic, ours, reference, tmp_path / "sr.png")


def test_pipeline_panel_with_the_tiled_difference(scene_images, tmp_path):
    reference = scene_images["reference"]
    images = {"noisy, bicubic 2x": scene_images["noisy"], "denoised + SR 2x": scene_images["ours"]}
    whole = scene_images["ours"][:16, :16]
    tiled = whole.copy()
    tiled[3, 4, 1] += 0.01
    tiled[5, 6, 0] -= 0.02
    panel = figures.pipeline_panel(images, reference, tmp_path / "pipeline.png", (tiled, whole))
    assert _png_shape(panel.path) == (round(figures.PANEL_INCHES * figures.DPI),
                                      round(4 * figures.PANEL_INCHES * figures.DPI))
    assert panel.extras["difference_max"] == pytest.approx(0.02)
    assert panel.psnr == {name: psnr(image, reference) for name, image in images.items()}
    signed = figures.signed_difference(tiled, whole)
    assert signed[5, 6] == pytest.approx(-0.02) and signed[3, 4] == pytest.approx(0.01) and signed[0, 0] == 0
    without = figures.pipeline_panel(images, reference, tmp_path / "plain.png")
    assert without.extras == {} and _png_shape(without.path)[1] == round(3 * figures.PANEL_INCHES * figures.DPI)
    with pytest.raises(ValueError, match="differ in shape"):
        figures.pipeline_panel(images, reference, tmp_path / "p.png", (tiled, whole[:8]))


@pytest.mark.parametrize("function", ["denoising", "superres", "pipeline"])
def test_mismatched_shapes_raise(function, scene_images, tmp_path):
    reference, ours = scene_images["reference"], scene_images["ours"][:, :24]
    with pytest.raises(ValueError, match="shape"):
        if function == "denoising":
            figures.denoising_panel({"ours": ours}, reference, tmp_path / "x.png")
        elif function == "superres":
            figures.superres_panel(reference[:16, :16], reference, ours, reference, tmp_path / "x.png")
        else:
            figures.pipeline_panel({"ours": ours}, reference, tmp_path / "x.png")
    assert not (tmp_path / "x.png").exists()


def test_empty_and_malformed_input_raise(scene_images, tmp_path):
    reference = scene_images["reference"]
    with pytest.raises(ValueError, match="no images"):
        figures.denoising_panel({}, reference, tmp_path / "x.png")
    with pytest.raises(ValueError, match="no images"):
        figures.pipeline_panel({}, reference, tmp_path / "x.png")
    with pytest.raises(ValueError, match="no histories"):
        figures.training_curves({}, tmp_path / "x.png")
    with pytest.raises(ValueError, match="no paths"):
        figures.markdown_links({}, tmp_path)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        figures.denoising_panel({"ours": np.zeros((SIDE, SIDE, 2))}, reference, tmp_path / "x.png")
    with pytest.raises(ValueError, match="named like the reference"):
        figures.denoising_panel({"reference": reference}, reference, tmp_path / "x.png")


def test_a_png_over_the_size_limit_is_palette_encoded(scene_images, tmp_path, monkeypatch):
    from PIL import Image

    images = {"noisy": scene_images["noisy"], "ours": scene_images["ours"]}
    full = figures.denoising_panel(images, scene_images["reference"], tmp_path / "full.png").path.stat().st_size
    monkeypatch.setattr(figures, "MAX_PNG_BYTES", full - 1)
    small = figures.denoising_panel(images, scene_images["reference"], tmp_path / "small.png").path
    assert small.stat().st_size < full
    with Image.open(small) as image:
        assert image.mode == "P"
    monkeypatch.setattr(figures, "MAX_PNG_BYTES", 1)
    with pytest.warns(RuntimeWarning, match="colour palette"):
        assert figures.denoising_panel(images, scene_images["reference"], tmp_path / "tiny.png").path.is_file()


def _history(epochs: int, scale: float) -> list[dict[str, float]]:
    return [{"epoch": e, "train_loss": scale / e, "validation_loss": scale / e + 0.01 * (e == epochs),
             "train_psnr": 30 + e, "validation_psnr": 29 + e, "seconds": 1.0} for e in range(1, epochs + 1)]


def test_training_curves(tmp_path):
    histories = {"cbox-original": _history(5, 1.0), "mixed": _history(4, 2.0), "superresolution": _history(6, 0.1)}
    path = figures.training_curves(histories, tmp_path / "training.png")
    assert _png_shape(path) == (4 * figures.DPI, 11 * figures.DPI)
    with pytest.raises(ValueError, match="validation_psnr"):
        figures.training_curves({"broken": [{k: v for k, v in row.items() if k != "validation_psnr"}
                                            for row in _history(3, 1.0)]}, tmp_path / "x.png")
    with pytest.raises(ValueError, match="no epochs"):
        figures.training_curves({"empty": []}, tmp_path / "x.png")


def test_markdown_links(tmp_path):
    paths = {"cbox-original-denoising": tmp_path / "figures" / "cbox-original-denoising.png",
             "Figure [4]": tmp_path / "training.png"}
    text = figures.markdown_links(paths, tmp_path)
    assert text == "![cbox-original-denoising](figures/cbox-original-denoising.png)\n![Figure 4](training.png)\n"


def _seeded_networks():
    from reconstruction.models import Denoiser, Superresolution

    torch.manual_seed(0)
    denoiser, superres = Denoiser(), Superresolution()
    torch.nn.init.normal_(denoiser.out.weight, std=0.05)  # the residual output starts at zero: make it do something
    return denoiser, superres


def test_pipeline_stages_give_equal_tiled_and_whole_outputs():
    denoiser, superres = _seeded_networks()
    rng = np.random.default_rng(1)
    noisy = rng.random((64, 64, 3)).astype(np.float32)
    albedo = rng.random((64, 64, 3)).astype(np.float32)
    images, (tiled, whole) = figures.pipeline_stages(noisy, albedo, denoiser, superres, tile=32)
    assert list(images) == ["noisy, bicubic 2x", "denoised, bicubic 2x", "denoised + SR 2x"]
    assert all(image.shape == (128, 128, 3) for image in images.values())
    assert tiled.shape == whole.shape == (64, 64, 3) and np.max(np.abs(tiled - whole)) < 1e-4


def test_scene_figures_on_the_cached_quick_dataset(tmp_path):
    pytest.importorskip("mitsuba")
    from kdtrace.config import DEFAULT_CONFIG
    from kdtrace.scenes import load_scene
    from reconstruction.data import dataset_dir, generate_dataset

    profile = DEFAULT_CONFIG.reconstruction.profile("quick")
    if not (dataset_dir(load_scene("cbox-original"), profile) / "manifest.json").is_file():
        pytest.skip("the quick cbox-original dataset is not cached (run `kdtrace report` first); not rendering it here")
    dataset = generate_dataset("cbox-original", profile, progress=False)
    denoiser, superres = _seeded_networks()
    paths = figures.scene_figures("cbox-original", dataset, {"ours": denoiser}, superres, tmp_path, oidn=HAVE_OIDN)
    assert list(paths) == ["cbox-original-denoising", "cbox-original-superres"]
    columns = 3 + HAVE_OIDN  # noisy, ours, OIDN, reference
    height = round(2 * figures.PANEL_INCHES * figures.DPI + 0.3 * figures.DPI)
    assert _png_shape(paths["cbox-original-denoising"]) == (height, round(columns * figures.PANEL_INCHES * figures.DPI))
    assert _png_shape(paths["cbox-original-superres"]) == (height, round(4 * figures.PANEL_INCHES * figures.DPI))
    for path in paths.values():
        assert path.parent == tmp_path / "figures" and path.stat().st_size < figures.MAX_PNG_BYTES
    assert figures.figure_view(dataset) == sorted(dataset.views("test"))[0]
    with pytest.raises(ValueError, match="not an accepted view"):
        figures.scene_figures("cbox-original", dataset, {"ours": denoiser}, superres, tmp_path, view="view-9999")
    links = figures.markdown_links(paths, tmp_path)
    assert "](figures/cbox-original-superres.png)" in links
