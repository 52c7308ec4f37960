"""`kdtrace compare`: every metric of a user's two images, both spaces, and the FLIP map."""

from __future__ import annotations

import numpy as np
import pytest

from kdtrace.cli import main
from kdtrace.imageio import read_image, write_exr, write_png
from reconstruction import metrics


@pytest.fixture
def pair(tmp_path):
    rng = np.random.default_rng(1)
    reference = np.full((24, 24, 3), 0.01)
    reference[:6] = 0.2
    test = reference * rng.uniform(0.5, 1.5, reference.shape)
    write_exr(tmp_path / "reference.exr", reference)
    np.save(tmp_path / "test.npy", test)
    return tmp_path, test, reference.astype(np.float32).astype(np.float64)


def test_prints_both_spaces_with_the_tonemapping_and_writes_the_flip_map(pair, capsys):
    folder, test, reference = pair
    assert main(["compare", str(folder / "test.npy"), str(folder / "reference.exr"), "--map", str(folder / "m.png")]) == 0
    out = capsys.readouterr().out
    expected = metrics.all_metrics(test, reference)
    assert f"exposure {expected['exposure']:.6g} (the reference's 99th-percentile luminance to 1)" in out
    for label, key in (("| linear (clipped to [0, 1]) | PSNR (dB)", "psnr"), ("| HDR (unclipped)            | relMSE", "relmse"),
                       ("| HDR (unclipped)            | SMAPE", "smape"), ("| display                    | PSNR (dB)", "display_psnr"),
                       ("| display                    | FLIP (LDR, 67 ppd)", "flip")):
        line = next(line for line in out.splitlines() if line.startswith(label))
        assert float(line.split("|")[3]) == pytest.approx(expected[key], rel=1e-5)
    shown, _ = read_image(folder / "m.png")
    assert shown.shape == (24, 24, 3)
    # an explicit exposure is what the display metrics use
    assert main(["compare", str(folder / "test.npy"), str(folder / "reference.exr"), "--exposure", "2"]) == 0
    assert "exposure 2 (--exposure)" in capsys.readouterr().out


def test_display_encoded_images_compare_as_they_are_shown(tmp_path, capsys):
    image = np.linspace(0, 1, 16 * 16 * 3).reshape(16, 16, 3)
    write_png(tmp_path / "a.png", image)
    write_png(tmp_path / "b.png", image * 0.9)
    assert main(["compare", str(tmp_path / "b.png"), str(tmp_path / "a.png")]) == 0
    assert "exposure 1 (1: the reference is a display-encoded image)" in capsys.readouterr().out
    decoded, encoded = read_image(tmp_path / "a.png")
    assert encoded and np.abs(decoded - image).max() < 0.01  # 8-bit sRGB round trip


def test_bad_input_is_one_clear_line_and_exit_2(pair, tmp_path, capsys):
    folder, _, _ = pair
    np.save(folder / "small.npy", np.ones((8, 8, 3)))
    np.save(folder / "nan.npy", np.full((24, 24, 3), np.nan))
    np.save(folder / "cube.npy", np.ones((4, 4, 4, 4)))
    (folder / "notes.txt").write_text("hello")
    (folder / "broken.png").write_bytes(b"\x89PNG not really")
    cases = [(["nope.exr", "reference.exr"], "nope.exr: no such file"),
             (["small.npy", "reference.exr"], "must have the same size"),
             (["nan.npy", "reference.exr"], "nan.npy: 1728 NaN/inf values"),
             (["cube.npy", "reference.exr"], "expected an image of shape"),
             (["notes.txt", "reference.exr"], "unknown image type '.txt'"),
             (["broken.png", "reference.exr"], "broken.png: cannot be read as an image")]
    for names, message in cases:
        assert main(["compare", *(str(folder / name) for name in names)]) == 2
        err = capsys.readouterr().err
        assert message in err and "Traceback" not in err
    assert main(["compare", str(folder / "test.npy"), str(folder / "reference.exr"), "--exposure", "nan"]) == 2
    assert "--exposure: must be a positive finite number" in capsys.readouterr().err
    np.save(folder / "black.npy", np.zeros((24, 24, 3)))
    assert main(["compare", str(folder / "test.npy"), str(folder / "black.npy")]) == 2
    assert "black.npy: no exposure" in capsys.readouterr().err
