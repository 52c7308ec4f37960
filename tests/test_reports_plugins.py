"""``kdtrace report --accelerator NAME --denoiser NAME``: plug-ins' rows in Table 1, agreement, Tables 2/6, error_time.

One tiny one-scene report (``cbox-original``) through the command line, with the example
plug-ins (``examples/kdtrace-example-plugins``, named by ``module:factory`` with their
source folder on ``sys.path``) and two broken ones (an accelerator answering a triangle
index past the scene's, a denoiser returning float64). Table 1 and the Embree half of the
agreement part run for real on tiny ray counts (the Mitsuba Z-test is left out: it has
its own tests). So that the test stays under a minute on 2 busy cores, our own networks
are not trained: the reconstruction part gets synthetic measurements of them (as in
``tests/test_reports_reconstruction.py``) and the sweep a synthetic row of our methods,
while the plug-in denoisers are measured for real, on test views and a frame rendered by
our path tracer (the sweep's Mitsuba reference is replaced by a 64-spp render of ours).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from kdtrace.cli import main as cli_main
from reports import agreement, error_time_curves, gate
from reports import error_time as et
from reports import reconstruction_tables as rt
from reports.metrics import read_metrics
from reports.plugins import is_plugin_metric, metric_name, parse_specs

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES_SRC = ROOT / "examples" / "kdtrace-example-plugins" / "src"
BRUTE_FORCE = "kdtrace_example_plugins.brute_force:make"
BILATERAL = "kdtrace_example_plugins.bilateral:make"
BROKEN_ACCELERATOR = "tests.test_reports_plugins:broken_accelerator"
BROKEN_DENOISER = "tests.test_reports_plugins:broken_denoiser"
SCENE, SIZE, SPP = "cbox-original", 32, (1, 4)

TINY = f"""
[profiles.tiny]
scenes = ["{SCENE}"]
agreement_rays_per_kind = 500
timing_rays = 1000
frame_width = 16
frame_height = 16
frame_spp = 2
reconstruction_profile = "quick"
reconstruction_scenes = ["{SCENE}"]
unseen_scene = ""
far_unseen_scene = ""
sweep_spp = [{SPP[0]}, {SPP[1]}]
sweep_width = {SIZE}
sweep_height = {SIZE}
sweep_reference_spp = 64
"""


# ------------------------------------------------------------------ broken plug-ins (named by spec below)
class _OutOfRange:
    """Answers every ray with the triangle index one past the scene's last."""

    def __init__(self, n_triangles: int) -> None:
        self.n = n_triangles

    def intersect(self, origins, directions, tmin=0.0, tmax=np.inf):
        n = len(origins)
        return np.ones(n), np.full(n, self.n, np.int32), np.zeros(n), np.zeros(n)

    def occluded(self, origins, directions, tmax):
        return np.zeros(len(origins), bool)


def broken_accelerator(scene) -> _OutOfRange:
    return _OutOfRange(len(scene.triangles))


def broken_denoiser():
    return lambda color, albedo, normal: color.astype(np.float64)


# ------------------------------------------------------------------ stand-ins for our own (trained) methods
def _render(spp: int, seed: int):
    from kdtrace.render import render
    from kdtrace.scenes import load_scene

    return render(load_scene(SCENE), spp=spp, max_depth=3, seed=seed, width=SIZE, height=SIZE, aux=True)


class _Views:
    """A dataset stand-in: two test views rendered by our path tracer (2 spp, 64-spp references)."""

    def __init__(self) -> None:
        self._views = {}
        for index in range(2):
            noisy, reference = _render(2, 10 + index), _render(64, 100 + index)
            self._views[f"view{index}"] = {"noisy": noisy.rgb, "albedo": noisy.albedo, "normal": noisy.normal,
                                           "reference": reference.rgb}

    def views(self, split=None):
        return sorted(self._views) if split in (None, "test") else []

    def load_view(self, name):
        return {key: np.array(value, np.float32) for key, value in self._views[name].items()}


def _pooled(psnr: float) -> dict[str, float]:
    return {"psnr": psnr, "rmse": 10 ** (-psnr / 20), "psnr_mean": psnr, "images": 2, "pixels": 2 * SIZE * SIZE * 3,
            "display_psnr": psnr - 6, "display_rmse": 10 ** (-(psnr - 6) / 20), "flip": 1.0 / psnr,
            "relmse": 10 ** (-psnr / 10), "smape": 0.1, "beyond_input": 0, "black_where_lit": 0}


def _reconstruction_stand_in(config, profile_name, fresh, progress, denoisers=()):
    """Synthetic measurements of our networks; the plug-in denoisers measured for real."""
    from reconstruction.speed import Frame

    quality = {SCENE: {"views": {"train": 4, "validation": 1, "test": 2},
                       "ours": {split: {"noisy": _pooled(20.0), "ours": _pooled(28.0),
                                        **({"oidn": _pooled(29.0)} if split == "test" else {})}
                                for split in ("train", "validation", "test")},
                       "mixed": {split: _pooled(27.0) for split in ("train", "validation", "test")},
                       "superres": {"bicubic": _pooled(30.0), "lanczos": _pooled(30.1), "ours": _pooled(31.0)}}}
    timing = {SCENE: {"threads": 2, "denoise_option": "fp32", "superres_option": "fp32", "decisions": {},
                      "denoise": {"ours_seconds": 0.01, "oidn_seconds": 0.02, "oidn_over_ours": 2.0, "noisy_psnr": 20.0,
                                  "ours_psnr": 28.0, "oidn_psnr": 29.0, "pixels": SIZE * SIZE},
                      "superres": {"ours_seconds": 0.02, "bicubic_seconds": 0.001, "bicubic_over_ours": 0.05,
                                   "ours_gflop": 1.0, "ours_gflops": 50.0, "matmul_gflops": 100.0,
                                   "floor_seconds": 0.01}}}
    photos = {split: {m: _pooled(30.0) for m in ("bicubic", "lanczos", "ours")} for split in ("train", "validation", "test")}
    m = {"profile": profile_name, "reconstruction_profile": "quick", "scenes": [SCENE], "unseen": "", "far": "",
         "frame": [SIZE, SIZE], "frame_spp": 2, "stages": [{"name": f"denoiser {SCENE}", "seconds": 1.0, "reused": True},
                                                          {"name": "mixed denoiser", "seconds": 1.0, "reused": True}],
         "epochs": {"per-scene denoisers": 2, "mixed": 2, "superresolution": 2}, "best_epochs": {SCENE: 2},
         "parameters": {"denoiser": 10, "superres": 5}, "quality": quality,
         "unseen_quality": None, "far_quality": None, "photos": photos, "timing": timing}
    noisy, reference = _render(2, 7), _render(64, 8)
    frame = Frame(SCENE, *(np.asarray(a, np.float32) for a in (noisy.rgb, noisy.albedo, noisy.normal, reference.rgb)),
                  2, 64)
    m["plugin_denoisers"] = rt.measure_plugin_denoisers(list(denoisers), [SCENE], {SCENE: _Views()}, {SCENE: frame}, timing)
    return m, {}


def _sweep_stand_in(kind, version, measure_scene, config, profile_name, out_dir, fresh, progress, blend_spp=(),
                    variant_scenes=None):
    """A synthetic row of our methods (each spp quadruples the seconds and adds 6 dB)."""
    points = []
    for method in error_time_curves.METHODS:
        for index, spp in enumerate(SPP):
            point = {"method": method, "spp": spp, "width": SIZE, "height": SIZE, "paths": SIZE * SIZE * spp,
                     "render_seconds": 0.001 * 4**index, "reconstruction_seconds": 0.0, "seconds": 0.001 * 4**index,
                     "psnr": 18.0 + 6 * index + (6 if "+" in method else 0), "relmse": 0.1 / 4**index}
            if "+" in method:
                point["input_psnr"] = 18.0 + 6 * index
            if method == "kdtrace+denoiser-blend":
                point["weight"] = 0.9
            points.append(point)
    return [{"scene": SCENE, "triangles": 36, "width": SIZE, "height": SIZE, "max_depth": 3,
             "reference": {"spp": 64, "seconds": 1.0, "variant": "stand-in", "relmse_floor": 1e-4, "psnr_ceiling": 45.0},
             "mitsuba_variant": "stand-in", "mitsuba_threads": 2, "torch_threads": 2, "points": points, "warnings": [],
             "load_average": [1.0, 1.0]}]


def _reference_stand_in(scene, spp, max_depth, seed, width=None, height=None, variant=None, cache=True):
    from references.mitsuba import Reference

    result = _render(spp, seed + 1000)  # not the seed of the sweep's frames: independent samples
    return Reference(result.rgb, np.full_like(result.rgb, 1e-4), spp, result.seconds, "our path tracer (test)", {})


# ------------------------------------------------------------------ the test
def test_report_puts_plugins_through_every_part(shared_scenes, isolated_cache, tmp_path, monkeypatch, capsys):
    monkeypatch.syspath_prepend(str(EXAMPLES_SRC))
    monkeypatch.setattr(agreement, "ztest_scenes", lambda scenes: [])
    monkeypatch.setattr(rt, "_measure", _reconstruction_stand_in)
    monkeypatch.setattr(rt, "write_figures", lambda *args, **kwargs: [])
    monkeypatch.setattr(et, "scene_rows", _sweep_stand_in)
    monkeypatch.setattr("references.mitsuba.render_reference", _reference_stand_in)
    (tmp_path / "tiny.toml").write_text(TINY)
    out = tmp_path / "report"
    out.mkdir()
    (out / "table1_production.md").write_text("# from an earlier `kdtrace production`\n")  # kept, and linked
    started = time.perf_counter()
    status = cli_main(["--config", str(tmp_path / "tiny.toml"), "report", "--profile", "tiny", "--out", str(out),
                       "--parts", "table1,agreement,reconstruction,error_time",
                       "--accelerator", f"{BRUTE_FORCE},{BROKEN_ACCELERATOR}", "--denoiser", BILATERAL,
                       "--denoiser", BROKEN_DENOISER])
    print(f"\n[plug-in report] {time.perf_counter() - started:.1f} s")
    printed = capsys.readouterr().out
    # the broken plug-ins' "failed" metrics are correctness failures: the run fails, naming them
    assert status == 1
    assert f"FAIL: table1/{SCENE}/plugin:{BROKEN_ACCELERATOR}/failed" in printed
    assert f"FAIL: table2/{SCENE}/plugin:{BROKEN_DENOISER}/failed" in printed
    assert "FAIL: table1/" + SCENE + "/unexplained" not in printed  # our own rows are unaffected
    bad_tri = f"plug-in {BROKEN_ACCELERATOR!r}: intersect returned tri[0] = "
    bad_dtype = f"plug-in {BROKEN_DENOISER!r}: the denoiser must return a float32 array of shape"
    metrics = {m.name: m for m in (m for path in (out / "metrics").glob("*.json") for m in read_metrics(path))}

    # Table 1: our row as always, the plug-in's row with finite numbers, the broken one failed
    ours = pd.read_csv(out / "table1.csv")
    assert list(ours["scene"]) == [SCENE] and ours["local_triangle_references"].iloc[0] > 0
    assert np.isfinite(ours["primary_local_over_embree"]).all()
    plugins = pd.read_csv(out / "table1_plugins.csv").set_index("plugin")
    good = plugins.loc[BRUTE_FORCE]
    for column in ("load_seconds", "primary_mrays_plugin", "incoherent_mrays_plugin", "primary_plugin_over_embree",
                   "incoherent_plugin_over_embree"):
        assert math.isfinite(good[column]) and good[column] > 0, column
    assert good["references"] == good["triangles"] and good["unexplained"] == 0 and good["wrong"] == 0
    assert plugins.loc[BROKEN_ACCELERATOR, "failed"].startswith("failed: " + bad_tri)
    table1 = (out / "table1.md").read_text()
    assert "## Plug-in accelerators" in table1 and BRUTE_FORCE in table1 and bad_tri in table1
    assert "[table1_production.md](table1_production.md)" in table1
    assert metrics[metric_name("table1", SCENE, BRUTE_FORCE, "over_embree_primary")].kind == "ratio"
    assert metrics[metric_name("table1", SCENE, BRUTE_FORCE, "wrong_hits")].value == 0
    assert metrics[f"table1/{SCENE}/wrong_hits"].value == 0 and metrics[f"table1/{SCENE}/unexplained_disagreements"].value == 0

    # agreement: the same classes for the plug-in, its failure for the broken one
    assert metrics[f"agreement/{SCENE}/unexplained_embree"].value == 0
    assert metrics[metric_name("agreement", SCENE, BRUTE_FORCE, "unexplained_embree")].value == 0
    assert metrics[metric_name("agreement", SCENE, BRUTE_FORCE, "wrong_embree")].value == 0
    classes = pd.read_csv(out / "agreement_plugins.csv").set_index("plug-in")
    assert classes.loc[BRUTE_FORCE, "rays compared"] > 0 and classes.loc[BRUTE_FORCE, "status"] == "ok"
    assert bad_tri in classes.loc[BROKEN_ACCELERATOR, "status"]
    assert "## Plug-in accelerators: disagreements" in (out / "agreement.md").read_text()

    # Tables 2 and 6: the bilateral filter on the same test views and frame, the float64 denoiser failed
    table2 = pd.read_csv(out / "table2.csv").set_index(["scene", "model"])
    assert table2.loc[(SCENE, "per-scene"), "test_psnr"] == pytest.approx(28.0)
    row = table2.loc[(SCENE, f"plug-in {BILATERAL}")]
    assert math.isfinite(row["test_psnr"]) and math.isfinite(row["minus_oidn"]) and row["test_views"] == 2
    assert bad_dtype in table2.loc[(SCENE, f"plug-in {BROKEN_DENOISER}"), "model_source"]
    table6 = pd.read_csv(out / "table6_plugins.csv").set_index("plug-in")
    assert table6.loc[BILATERAL, "plugin_denoise_s"] > 0 and math.isfinite(table6.loc[BILATERAL, "oidn_over_plugin"])
    assert bad_dtype in table6.loc[BROKEN_DENOISER, "status"]
    assert "## Plug-in denoisers" in (out / "table6.md").read_text()
    assert metrics[metric_name("table2", SCENE, BILATERAL, "test_psnr")].kind == "psnr"
    assert metrics[metric_name("table6", SCENE, BILATERAL, "oidn_over_plugin_seconds")].kind == "ratio"
    assert metrics[f"table6/{SCENE}/oidn_over_ours_seconds"].value == pytest.approx(2.0)

    # error_time: kdtrace+SPEC at every sweep spp, in the CSV, tables, headline; the failure stated
    points = pd.read_csv(out / "error_time.csv")
    plugin_points = points[points["method"] == f"kdtrace+{BILATERAL}"]
    assert sorted(plugin_points["spp"]) == list(SPP)
    assert np.isfinite(plugin_points[["psnr", "relmse", "seconds", "input_psnr"]]).all().all()
    assert (plugin_points["reconstruction_seconds"] > 0).all() and (plugin_points["seconds"] > plugin_points["render_seconds"]).all()
    assert set(error_time_curves.METHODS) <= set(points["method"]) and f"kdtrace+{BROKEN_DENOISER}" not in set(points["method"])
    markdown = (out / "error_time.md").read_text()
    label = f"ours + plug-in {BILATERAL}"
    headline = markdown.split("## Headline")[1].split(f"## {SCENE}")[0]
    assert label in headline and f"speed-up of {label} over Mitsuba" in markdown
    assert f"Plug-in {BROKEN_DENOISER}: failed: " in markdown and bad_dtype in markdown
    assert metrics[metric_name("error_time", SCENE, BILATERAL, "psnr_4spp")].kind == "psnr"
    assert metrics[metric_name("error_time", SCENE, BROKEN_DENOISER, "failed")].value == 1
    assert (out / "error_time" / f"{SCENE}.png").read_bytes()[:4] == b"\x89PNG"

    # the index names the failures; the baseline never takes the plug-ins' metrics
    index = (out / "README.md").read_text()
    assert bad_tri in index and bad_dtype in index
    assert json.loads((out / "provenance.json").read_text())["plugins"]["denoisers"] == [BILATERAL, BROKEN_DENOISER]
    monkeypatch.setattr(gate, "BASELINE_DIR", tmp_path / "baseline")
    paths, _ = gate.update_baseline(out, "tiny")
    stored = {name: metric for path in paths for name, metric in gate.read_baseline(path).items()}
    assert f"table1/{SCENE}/wrong_hits" in stored and not any(is_plugin_metric(name) for name in stored)
    assert any(is_plugin_metric(name) for name in metrics)


def test_plugin_rows_are_cached_apart_and_our_keys_do_not_change(shared_scenes, isolated_cache, tmp_path, monkeypatch):
    """A plug-in row is reused by spec; our rows' keys and values are those of a run without plug-ins."""
    import dataclasses

    from kdtrace.config import load_config
    from reports import table1

    monkeypatch.syspath_prepend(str(EXAMPLES_SRC))
    config = load_config()
    small = dataclasses.replace(config.profile("quick"), scenes=("cbox-empty",), agreement_rays_per_kind=300,
                                timing_rays=500, frame_width=8, frame_height=8, frame_spp=1)
    config = dataclasses.replace(config, profiles={"tiny": small})
    table1.generate(config, "tiny", tmp_path, progress=False)
    ours = json.loads((tmp_path / "rows" / "cbox-empty.json").read_text())
    with pytest.warns(Warning) as caught:
        table1.generate(config, "tiny", tmp_path, progress=False, accelerators=[BRUTE_FORCE])
    assert any("reused 1 of 1 scene rows" in str(w.message) for w in caught)
    assert json.loads((tmp_path / "rows" / "cbox-empty.json").read_text()) == ours  # not measured again
    with pytest.warns(Warning) as caught:
        metrics = table1.generate(config, "tiny", tmp_path, progress=False, accelerators=[BRUTE_FORCE])
    assert any("reused 1 of 1 plug-in rows" in str(w.message) for w in caught)
    assert metrics[-1].name.startswith(f"table1/cbox-empty/plugin:{BRUTE_FORCE}/")


def test_specs_parse_like_the_bench_options_and_unknown_ones_fail_first(tmp_path, capsys):
    assert parse_specs(["a,b", "b", " c ,", "a"]) == ["a", "b", "c"]
    assert parse_specs(None) == []
    assert is_plugin_metric(metric_name("table1", "s", "m.n:make", "wrong_hits"))
    assert not is_plugin_metric("table1/s/wrong_hits")
    status = cli_main(["report", "--parts", "table1", "--out", str(tmp_path), "--accelerator", "no_such_module_xyz:make"])
    assert status == 2 and "plug-in 'no_such_module_xyz:make': cannot import it" in capsys.readouterr().err
    assert not (tmp_path / "table1.md").exists()
