"""Tables 2, 3, 5, 6 and the quality table (``reports/reconstruction_tables.py``).

The fast test writes the tables from a synthetic set of measurements (no training): the
files, the paper's figures beside ours, the reuse notes, the derived columns
(differences, pooled rows, ratios) and the gated metrics. The end-to-end test runs the
whole thing twice on a tiny profile (32x32 views, 2 epochs) in a private cache: the
second run must reuse every dataset and model, say so, and give the same PSNRs (about
25 s on 2 idle cores: 15 s, then 6 s for the rerun).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from kdtrace.config import DEFAULT_CONFIG, load_config
from reconstruction.train import resolve_precision
from reports import reconstruction_tables as rt
from reports.metrics import read_metrics
from reports.paper_figures import TABLE2, TABLE3

SCENES = ["cbox-sphere", "car"]
UNSEEN = "samurai-monastery"


def _pooled(psnr: float, images: int = 2, pixels: int = 2 * 64 * 64 * 3) -> dict[str, float]:
    display = psnr - 6  # a display-referred PSNR of the same images, lower as on real dark scenes
    return {"psnr": psnr, "rmse": 10 ** (-psnr / 20), "psnr_mean": psnr + 1, "images": images, "pixels": pixels,
            "display_psnr": display, "display_rmse": 10 ** (-display / 20), "flip": 1.0 / psnr, "relmse": 10 ** (-psnr / 10),
            "smape": 0.1, "beyond_input": 0, "black_where_lit": 0}


def _measurements() -> dict:
    quality = {}
    for offset, name in enumerate(SCENES):
        base = 30.0 + offset
        quality[name] = {
            "views": {"train": 4, "validation": 1, "test": 2},
            "ours": {"train": {"noisy": _pooled(base - 8), "ours": _pooled(base + 2)},
                     "validation": {"noisy": _pooled(base - 8), "ours": _pooled(base + 1)},
                     "test": {"noisy": _pooled(base - 8), "ours": _pooled(base), "oidn": _pooled(base + 0.5)}},
            "mixed": {split: _pooled(base - 1.5) for split in ("train", "validation", "test")},
            "superres": {"bicubic": _pooled(40.0), "lanczos": _pooled(40.2), "ours": _pooled(41.0)},
        }
    timing = {name: {"threads": 2, "denoise_option": "channels_last", "superres_option": "fp32", "decisions": {},
                     "denoise": {"ours_seconds": 0.1, "oidn_seconds": 0.3, "oidn_over_ours": 3.0, "noisy_psnr": 20.0,
                                 "ours_psnr": 30.0, "oidn_psnr": 31.0, "pixels": 65536},
                     "superres": {"ours_seconds": 0.2, "bicubic_seconds": 0.01, "bicubic_over_ours": 0.05,
                                  "ours_consistency_psnr": 45.0, "bicubic_consistency_psnr": 44.0,
                                  "output_pixels": 262144, "ours_gflop": 19.76, "ours_gflops": 98.8,
                                  "matmul_gflops": 120.0, "floor_seconds": 0.165}}
              for name in SCENES}
    stages = ([{"name": f"dataset {n}", "seconds": 1.0, "reused": True} for n in [*SCENES, UNSEEN]]
              + [{"name": f"denoiser {n}", "seconds": 0.5, "reused": True, "training_seconds": 30.4} for n in SCENES]
              + [{"name": "mixed denoiser", "seconds": 12.0, "reused": False},
                 {"name": "superresolution", "seconds": 0.5, "reused": True}])
    photos = {split: {"bicubic": _pooled(30.0), "lanczos": _pooled(30.1), "ours": _pooled(30.5)}
              for split in ("train", "validation", "test")}
    return {"profile": "quick", "reconstruction_profile": "quick", "scenes": SCENES, "unseen": UNSEEN,
            "frame": [256, 256], "frame_spp": 4, "stages": stages,
            "epochs": {"per-scene denoisers": 40, "mixed": 40, "superresolution": 40},
            "best_epochs": {"cbox-sphere": 30, "car": 20, "mixed": 40, "superres": 10},
            "parameters": {"denoiser": 95107, "superres": 37793}, "quality": quality,
            "unseen_quality": {"views": 7, "noisy": _pooled(20.0), "ours": _pooled(22.0), "oidn": _pooled(27.0)},
            "photos": photos, "timing": timing}


def test_tables_from_measurements(tmp_path):
    m = _measurements()
    frames = rt.write_outputs(m, DEFAULT_CONFIG, tmp_path)
    for stem in rt.TABLES:
        text = (tmp_path / f"{stem}.md").read_text()
        assert "Reused from the cache: 6 of 7 datasets and models; made in this run: mixed denoiser (12 s)." in text
        pd.testing.assert_frame_equal(pd.read_csv(tmp_path / f"{stem}.csv"), frames[stem], check_dtype=False)
    table2 = frames["table2"].set_index(["scene", "model"])
    assert table2.loc[("cbox-sphere", "per-scene"), "paper_test_psnr"] == TABLE2["cbox-sphere"]["test_psnr"]
    assert table2.loc[("cbox-sphere", "per-scene"), "model_source"] == "reused (trained 30 s)"
    assert table2.loc[("car", "mixed"), "model_source"] == "trained 12 s"
    # both scenes' mixed test views pooled: equal pixel counts, so the MSEs average
    expected = -10 * math.log10((10 ** (-28.5 / 10) + 10 ** (-29.5 / 10)) / 2)
    assert table2.loc[("all scenes", "mixed"), "test_psnr"] == pytest.approx(expected)
    assert table2.loc[("all scenes", "mixed"), "test_views"] == 4
    assert "cbox-sphere (CBox)" in (tmp_path / "table2.md").read_text()

    table3 = frames["table3"].set_index("scene")
    assert table3.loc["car", "psnr_difference"] == pytest.approx(1.5)
    assert table3.loc["car", "paper_psnr_difference"] == TABLE3["car"]["psnr_difference"]
    assert table3.loc[f"{UNSEEN} (never seen)", "mixed_psnr"] == pytest.approx(22.0)
    assert table3.loc[f"{UNSEEN} (never seen)", "views"] == "all (7)"
    assert table3.loc[f"{UNSEEN} (never seen)", "paper_mixed_psnr"] == TABLE3["unseen"]["test_psnr"]
    # the views of variants this run did not train are left out, not shown empty
    assert "### The perceptual mixed model" not in (tmp_path / "table3.md").read_text()
    assert "### The display-trained net" not in (tmp_path / "table5.md").read_text()

    table5 = frames["table5"]
    assert list(table5["data"]) == ["photos"] * 3 + SCENES + ["all scenes"]
    assert table5["gain_over_bicubic"].iloc[-1] == pytest.approx(1.0)
    table6 = frames["table6"].set_index("scene")
    assert table6.loc["car", "oidn_over_ours"] == pytest.approx(3.0)
    assert table6.loc["car", "paper_denoise_s"] == pytest.approx(1.92)
    assert table6.loc["car", "superres_floor_s"] == pytest.approx(0.165) and table6.loc["car", "matmul_gflops"] == 120.0
    quality = frames["quality"].set_index("scene")
    assert quality.loc["cbox-sphere", ["noisy", "ours", "mixed", "oidn"]].tolist() == pytest.approx([22, 30, 28.5, 30.5])
    provenance = json.loads((tmp_path / "reconstruction_provenance.json").read_text())
    assert provenance["profile"] == "quick" and provenance["machine"]["cores"] >= 1

    metrics = rt.metrics_of(m)
    by_name = {metric.name: metric for metric in metrics}
    assert by_name["table2/denoiser/parameters"].value == 95107 and by_name["table2/denoiser/parameters"].kind == "count"
    assert by_name["table2/car/ours_test_psnr"].value == pytest.approx(31.0)
    assert by_name["table2/car/mixed_test_psnr"].kind == "psnr"
    assert by_name["table6/car/oidn_over_ours_seconds"].kind == "ratio"
    assert by_name[f"table3/{UNSEEN}/mixed_psnr"].value == pytest.approx(22.0)
    # display-referred beside linear: the synthetic display PSNR is 6 dB below the linear one, FLIP 1/PSNR
    assert by_name["table2/car/ours_display_psnr"].value == pytest.approx(25.0)
    assert by_name["table2/car/ours_flip"].value == pytest.approx(1 / 31.0) and by_name["table2/car/ours_flip"].kind == "flip"
    assert by_name[f"table3/{UNSEEN}/mixed_display_psnr"].value == pytest.approx(16.0)
    assert {metric.kind for metric in metrics} == {"count", "psnr", "flip", "ratio"}
    # the Markdown puts the paper's PSNR beside our display-referred one, in tables of at most 8 columns
    text = (tmp_path / "table2.md").read_text()
    display = text[text.index("### Display-referred"):text.index("### Linear")]
    assert "paper PSNR" in display and "FLIP noisy / ours / OIDN" in display
    widths = {line.count("|") - 1 for line in text.splitlines() if line.startswith("|")}
    assert max(widths) <= 8


TINY = """
[profiles.tiny]
scenes = ["cbox-original"]
frame_width = 32
frame_height = 32
reconstruction_profile = "tiny"
reconstruction_scenes = ["cbox-original", "cbox-sphere"]
unseen_scene = "cbox-empty"
variant_scenes = ["cbox-original"]
demodulated_scenes = ["cbox-sphere"]
perceptual_mixed = true
superres_display = true

[reconstruction.profiles.tiny]
positions = 1
views_per_position = 3
width = 32
height = 32
spp = 2
reference_spp = 8
test_reference_spp_by_scene = { cbox-original = 16 }
crop_size = 16
crops_per_view = 4
epochs = 2
batch_size = 4
superres_crop_size = 16
superres_crops_per_image = 2
"""


def test_generate_end_to_end_and_reuse(tmp_path, monkeypatch, shared_scenes):
    pytest.importorskip("mitsuba")
    pytest.importorskip("pyoidn")
    from reconstruction import data, evaluate

    monkeypatch.setenv("KDTRACE_CACHE", str(tmp_path / "cache"))
    # The plumbing, not the numbers: two small training photos and one test photo (the
    # training set's retina alone is 2 megapixels, whose FLIP and SSIM took two thirds of this test).
    monkeypatch.setattr(data, "TRAIN_PHOTOS", ("astronaut", "coffee"))
    monkeypatch.setattr(evaluate, "TEST_PHOTOS", ("motorcycle_left",))
    (tmp_path / "tiny.toml").write_text(TINY)
    config = load_config(tmp_path / "tiny.toml")
    metrics = rt.generate(config, "tiny", tmp_path / "out", progress=False)
    assert "made in this run: dataset cbox-original" in (tmp_path / "out" / "table2.md").read_text()
    figures = (tmp_path / "out" / "figures.md").read_text()
    for stem in ("training", "cbox-original-denoising", "cbox-original-superres"):
        assert f"figures/{stem}.png" in figures and (tmp_path / "out" / "figures" / f"{stem}.png").is_file()
    again = rt.generate(config, "tiny", tmp_path / "out", progress=False)
    table2 = (tmp_path / "out" / "table2.md").read_text()
    assert "Reused from the cache: 12 of 12 datasets and models." in table2  # the refined test references too
    precision, why = resolve_precision(config.reconstruction.profile("tiny").precision)
    assert f"Training arithmetic on this machine: {why or precision}." in table2  # an fp32 fallback says why
    rows = pd.read_csv(tmp_path / "out" / "table2.csv").set_index(["scene", "model"])
    for scene, model in (("cbox-original", "per-scene +normal+depth"), ("cbox-sphere", "per-scene demodulated")):
        variant = rows.loc[(scene, model)]
        assert np.isfinite(variant["test_psnr"]) and variant["noisy_test_psnr"] > 0
    assert rows.loc[("cbox-original", "per-scene"), "test_reference_spp"] == 16  # refined
    assert rows.loc[("cbox-sphere", "per-scene"), "test_reference_spp"] == 8  # not needed, not rendered
    assert np.isfinite(rows.loc[("cbox-original", "per-scene"), "reference_margin_per_view_db"])
    assert ("cbox-sphere", "per-scene +normal+depth") not in rows.index
    assert ("cbox-original", "per-scene demodulated") not in rows.index
    from reconstruction.models import Denoiser
    from reconstruction.train import parameter_count

    normal_depth = next(v for v in rt.DENOISER_VARIANTS if v.key == "normal_depth")
    wider = parameter_count(Denoiser(normal_depth.auxiliary))
    assert wider > 95107 and f"({wider} parameters against the paper network's 95107)" in table2
    assert "the paper's network (95107 parameters) denoising the noisy colour divided by the albedo" in table2
    assert {m.name for m in metrics} >= {"table2/cbox-original/normal_depth_test_psnr",
                                         "table2/cbox-sphere/demodulated_test_psnr",
                                         "table3/cbox-empty/mixed_perceptual_display_psnr",
                                         "table3/cbox-sphere/mixed_perceptual_flip",
                                         "table5/cbox-sphere/display_trained_display_psnr",
                                         "table5/photos/display_trained_display_psnr"}
    table3 = pd.read_csv(tmp_path / "out" / "table3.csv").set_index("scene")
    assert np.isfinite(table3.loc["cbox-empty (never seen)", "mixed_perceptual_display_psnr"])
    assert "### The perceptual mixed model" in (tmp_path / "out" / "table3.md").read_text()
    assert "### The display-trained net" in (tmp_path / "out" / "table5.md").read_text()
    table5 = pd.read_csv(tmp_path / "out" / "table5.csv").set_index(["data", "split"])
    # the display-trained net's own baseline is bicubic of the displayed image, not of the radiance
    shown = table5.loc[("cbox-sphere", "test")]
    assert shown["displayed_gain_over_bicubic"] == pytest.approx(
        shown["displayed_ours_display_psnr"] - shown["displayed_bicubic_display_psnr"])
    assert shown["displayed_bicubic_display_psnr"] != pytest.approx(shown["bicubic_display_psnr"], abs=1e-6)
    psnrs = {m.name: m.value for m in metrics if m.kind == "psnr"}
    assert psnrs == {m.name: m.value for m in again if m.kind == "psnr"}  # same cached models, same numbers
    assert {m.name for m in read_metrics(tmp_path / "out" / "metrics" / "reconstruction.json")} == {m.name for m in again}


class _Views:
    """Stand-in dataset: named views with a noisy input and a reference."""

    def __init__(self, views):
        self._views = views

    def views(self, split):
        return list(self._views)

    def load_view(self, name):
        return self._views[name]


def test_reference_noise_per_view_and_pooled():
    reference = np.full((4, 4, 3), 0.5)
    # squared errors 0.01 and 0.04 between noisy input and reference; at 4 and 12 spp the
    # reference's own share of them is 4/16
    views = _Views({"a": {"noisy": reference + 0.1, "reference": reference},
                    "b": {"noisy": reference - 0.2, "reference": reference}})
    noise = rt.reference_noise(views, "test", spp=4, reference_spp=12)
    assert noise["views"] == 2
    assert noise["lowest_psnr"] == pytest.approx(-10 * math.log10(0.04 / 4))
    assert noise["pooled_psnr"] == pytest.approx(-10 * math.log10(0.025 / 4))
    assert noise["lowest_psnr"] < noise["pooled_psnr"] < -10 * math.log10(0.01 / 4)
    assert noise["psnrs"] == pytest.approx([-10 * math.log10(0.01 / 4), -10 * math.log10(0.04 / 4)])
    assert noise["reference_spp"] == 12


def test_the_per_view_margin_takes_each_views_best_method():
    noise = {"psnrs": [40.0, 50.0, 45.0]}
    ours, oidn, noisy = ({"per_image_psnr": values} for values in ([35.0, 47.0, 30.0], [36.0, 48.0, 41.0],
                                                                  [20.0, 25.0, 22.0]))
    # view by view: 40 - 36, 50 - 48, 45 - 41; without OIDN 40 - 35, 50 - 47, 45 - 30
    assert rt._per_view_margin(noise, ours, oidn, noisy) == pytest.approx(2.0)
    assert rt._per_view_margin(noise, ours, None, noisy) == pytest.approx(3.0)  # no OIDN on the row
    assert rt._per_view_margin(noise, ours, {"psnr": 40.0}, noisy) is None  # measured before per-view lists
    assert rt._per_view_margin({}, ours, oidn, noisy) is None


def test_every_table2_row_of_a_scene_gets_its_own_reference_margins():
    # a variant row is judged against the same references as the per-scene row, with its own best
    noise = {"psnrs": [50.0, 44.0], "lowest_psnr": 44.0, "pooled_psnr": 46.0, "reference_spp": 1024}
    quality = {"ours": {"test": {"noisy": {"psnr": 30.0, "per_image_psnr": [31.0, 29.0]},
                                 "oidn": {"psnr": 39.0, "per_image_psnr": [40.0, 38.0]}}},
               "reference_noise": noise}
    variant = {"psnr": 41.0, "rmse": 0.01, "per_image_psnr": [42.0, 39.5]}
    columns = rt._test_columns(quality, variant)
    assert columns["gain_over_noisy"] == pytest.approx(11.0) and columns["minus_oidn"] == pytest.approx(2.0)
    assert columns["reference_margin_db"] == pytest.approx(3.0)  # 44 - max(41, 39, 30)
    assert columns["reference_margin_pooled_db"] == pytest.approx(5.0)
    assert columns["reference_margin_per_view_db"] == pytest.approx(4.5)  # min(50 - 42, 44 - 39.5)
    assert columns["test_reference_spp"] == 1024
    unmeasured = rt._test_columns({"ours": {"test": {"noisy": {"psnr": 30.0}}}}, variant)
    assert unmeasured["oidn_test_psnr"] is None and unmeasured["reference_margin_db"] is None
    assert unmeasured["test_reference_spp"] is None
