"""Run time against error (``reports/error_time.py``): interpolation, equal-time and equal-error tables.

The pure logic is checked on synthetic curves with known answers (a power law is a
straight line in log-log, so interpolation between its points is exact); one small
end-to-end run on ``cbox-original`` at 32x32 with tiny networks checks the files, the
metrics and the reuse of cached rows.
"""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pandas as pd
import pytest

from kdtrace.config import ProfileConfig, ReconstructionConfig, load_config
from reports.error_time import generate
from reports.error_time_curves import (
    METHODS,
    Reach,
    common_seconds,
    equal_error_table,
    equal_time_table,
    headline,
    seconds_to_reach,
    speedup_cell,
    value_at_seconds,
)
from reports.metrics import read_metrics

SECONDS = [0.5, 1.0, 2.0, 4.0, 8.0]


def power_law(t):
    """relMSE = 0.1 / t: slope -1 in log-log."""
    return 0.1 / np.asarray(t, np.float64)


def psnr_line(t):
    """PSNR = 20 + 10 log10(t): a straight line over log seconds."""
    return 20.0 + 10.0 * np.log10(np.asarray(t, np.float64))


# ------------------------------------------------------------------ interpolation
@pytest.mark.parametrize("at", [0.7, 1.0, 3.0, 7.9])
def test_interpolation_is_exact_on_a_power_law_and_a_log_line(at):
    assert value_at_seconds(SECONDS, power_law(SECONDS), at, log_values=True) == pytest.approx(0.1 / at, rel=1e-12)
    assert value_at_seconds(SECONDS, psnr_line(SECONDS), at, log_values=False) == pytest.approx(float(psnr_line(at)), abs=1e-9)


def test_linear_interpolation_of_a_power_law_would_differ():
    # The log-log choice matters: between 1 s and 2 s a linear average gives 0.075, the power law 0.1/1.5.
    assert value_at_seconds(SECONDS, power_law(SECONDS), 1.5, log_values=True) == pytest.approx(0.1 / 1.5)
    assert 0.1 / 1.5 != pytest.approx(0.075)


def test_no_extrapolation_outside_the_measured_seconds():
    assert math.isnan(value_at_seconds(SECONDS, power_law(SECONDS), 0.49, log_values=True))
    assert math.isnan(value_at_seconds(SECONDS, psnr_line(SECONDS), 8.01, log_values=False))
    assert value_at_seconds(SECONDS, power_law(SECONDS), 8.0, log_values=True) == pytest.approx(0.1 / 8.0)


def test_unsorted_points_and_equal_seconds():
    order = [3, 0, 4, 1, 2]
    shuffled = [SECONDS[i] for i in order]
    assert value_at_seconds(shuffled, power_law(shuffled), 3.0, True) == pytest.approx(0.1 / 3.0)
    # Two points at the same seconds are averaged (geometric mean for log values).
    assert value_at_seconds([1.0, 1.0, 2.0], [0.1, 0.4, 0.1], 1.0, True) == pytest.approx(0.2)
    assert value_at_seconds([1.0, 1.0, 2.0], [30.0, 32.0, 40.0], 1.0, False) == pytest.approx(31.0)


def test_bad_curves_are_refused():
    with pytest.raises(ValueError, match="positive"):
        value_at_seconds([0.0, 1.0], [0.1, 0.05], 0.5, True)
    with pytest.raises(ValueError, match="positive values"):
        value_at_seconds([1.0, 2.0], [0.1, -0.05], 1.5, True)
    with pytest.raises(ValueError, match="matching"):
        value_at_seconds([1.0, 2.0], [0.1], 1.5, True)


# ------------------------------------------------------------------ equal error
def test_seconds_to_reach_interpolates_the_crossing():
    reach = seconds_to_reach(SECONDS, power_law(SECONDS), 0.1 / 3.0, higher_is_better=False)
    assert reach.kind == "exact" and reach.seconds == pytest.approx(3.0)
    reach = seconds_to_reach(SECONDS, psnr_line(SECONDS), 25.0, higher_is_better=True)
    assert reach.kind == "exact" and reach.seconds == pytest.approx(10 ** 0.5)


def test_not_reached_and_already_reached_are_stated_not_extrapolated():
    assert seconds_to_reach(SECONDS, psnr_line(SECONDS), 40.0, True) == Reach(None, "not reached")
    reach = seconds_to_reach(SECONDS, psnr_line(SECONDS), 10.0, True)
    assert reach == Reach(0.5, "at most")
    assert reach.cell() == "≤ 0.5" and Reach(None, "not reached").cell() == "not reached"
    assert Reach(3.14159, "exact").cell() == "3.14"


def test_first_crossing_of_a_non_monotone_curve_counts():
    seconds, psnr = [1.0, 2.0, 3.0, 4.0], [20.0, 31.0, 29.0, 36.0]
    assert seconds_to_reach(seconds, psnr, 30.0, True).seconds == pytest.approx(math.exp(np.log(2.0) * 10.0 / 11.0))
    # 35 dB: 29 dB at 3 s, 36 dB at 4 s; the brief dip below 30 dB does not matter.
    expected = math.exp(math.log(3.0) + 6.0 / 7.0 * (math.log(4.0) - math.log(3.0)))
    assert seconds_to_reach(seconds, psnr, 35.0, True).seconds == pytest.approx(expected)


def test_speedup_cells_state_bounds():
    exact = Reach(0.5, "exact")
    assert speedup_cell(Reach(2.0, "exact"), exact, 10.0) == "4x"
    assert speedup_cell(Reach(None, "not reached"), exact, 10.0) == "> 20x"
    assert speedup_cell(Reach(2.0, "exact"), Reach(0.5, "at most"), 10.0) == "≥ 4x"
    assert speedup_cell(Reach(0.25, "at most"), exact, 10.0) == "≤ 0.5x"
    assert speedup_cell(Reach(0.25, "at most"), Reach(0.5, "at most"), 10.0) == "—"
    assert speedup_cell(Reach(2.0, "exact"), Reach(None, "not reached"), 10.0) == "—"


def test_common_seconds_grid():
    assert common_seconds(0.004, 0.5) == [0.01, 0.03, 0.1, 0.3]
    assert common_seconds(1.0, 3.0) == [1.0, 3.0]
    assert common_seconds(1.5, 2.5) == []
    with pytest.raises(ValueError):
        common_seconds(0.0, 1.0)


def synthetic_points() -> pd.DataFrame:
    """Mitsuba: PSNR = 20 + 10 log10(t / 0.01) at 0.01..0.64 s; ours + denoiser: 31 dB at 0.05 s (4 spp)."""
    rows = []
    for spp, t in zip((1, 2, 4, 8, 16, 32, 64), 0.01 * 2.0 ** np.arange(7), strict=True):
        rows.append({"method": "mitsuba", "spp": spp, "seconds": t, "psnr": 20 + 10 * math.log10(t / 0.01),
                     "relmse": 0.1 * 0.01 / t})
    for spp, t, psnr in ((1, 0.04, 29.0), (4, 0.05, 31.0), (16, 0.08, 33.0)):
        rows.append({"method": "kdtrace+denoiser", "spp": spp, "seconds": t, "psnr": psnr, "relmse": 0.004})
    return pd.DataFrame(rows)


def test_tables_and_headline_on_synthetic_curves():
    points = synthetic_points()
    reach = equal_error_table(points, psnr_thresholds=(30.0, 35.0), relmse_thresholds=(0.01, 0.001))
    assert reach["mitsuba"]["linear 30 dB"].seconds == pytest.approx(0.1)
    assert reach["mitsuba"]["linear 35 dB"].seconds == pytest.approx(0.01 * 10**1.5)
    assert reach["kdtrace+denoiser"]["linear 35 dB"].kind == "not reached"
    assert reach["kdtrace+denoiser"]["relMSE 0.01"] == Reach(0.04, "at most")
    assert reach["mitsuba"]["relMSE 0.01"].seconds == pytest.approx(0.1)
    assert reach["mitsuba"]["relMSE 0.001"] == Reach(None, "not reached")  # would need 1 s; measured up to 0.64 s

    result = headline(points, 4, "kdtrace+denoiser")
    target = 10 ** ((31.0 - 20.0) / 10) * 0.01  # Mitsuba's seconds to 31 dB on its line
    assert result["reference"].seconds == pytest.approx(target)
    assert result["speedup"] == f"{target / 0.05:.3g}x"
    # at equal relMSE (lower is better): Mitsuba reaches 0.004 at 0.25 s on its 0.001/t line
    by_relmse = headline(points, 4, "kdtrace+denoiser", error="relmse")
    assert by_relmse["value"] == 0.004 and by_relmse["reference"].seconds == pytest.approx(0.25)
    assert by_relmse["speedup"] == f"{0.25 / 0.05:.3g}x"
    # the display space where the points have it: its own thresholds and curve
    shown = points.assign(display_psnr=points["psnr"] - 5.0)
    assert equal_error_table(shown, display_thresholds=(25.0,))["mitsuba"]["display 25 dB"].seconds == pytest.approx(0.1)
    assert headline(shown, 4, "kdtrace+denoiser", error="display_psnr")["reference"].seconds == pytest.approx(target)

    table = equal_time_table(points, [0.01, 0.05, 1.0])
    ours = table[table["method"] == "kdtrace+denoiser"].set_index("seconds")
    assert math.isnan(ours.loc[0.01, "psnr"]) and ours.loc[0.05, "psnr"] == pytest.approx(31.0)
    theirs = table[table["method"] == "mitsuba"].set_index("seconds")
    assert theirs.loc[0.05, "psnr"] == pytest.approx(20 + 10 * math.log10(5)) and math.isnan(theirs.loc[1.0, "psnr"])


# ------------------------------------------------------------------ end to end
def tiny_config(spp=(1, 4)):
    """The default configuration plus a ``tiny`` report profile on cbox-original with tiny networks (seconds to train)."""
    config = load_config()
    recon = dataclasses.replace(config.reconstruction.profile("quick"), positions=1, views_per_position=4, width=32,
                                height=32, reference_spp=16, crop_size=32, crops_per_view=2, epochs=2,
                                superres_crop_size=16, superres_crops_per_image=2)
    profile = ProfileConfig(scenes=("cbox-original",), reconstruction_profile="tiny",
                            reconstruction_scenes=("cbox-original",), demodulated_scenes=("cbox-original",),
                            perceptual_scenes=("cbox-original",),
                            sweep_spp=spp, sweep_width=32, sweep_height=32,
                            sweep_reference_spp=32, combined_width=32, combined_height=32)
    return dataclasses.replace(config, reconstruction=ReconstructionConfig({"tiny": recon}), profiles={"tiny": profile})


def test_generate_end_to_end_and_reuse(shared_scenes, isolated_cache, tmp_path, capsys):
    pytest.importorskip("mitsuba")
    pytest.importorskip("pyoidn")
    config, out = tiny_config(), tmp_path / "report"
    metrics = generate(config, "tiny", out, progress=False)

    names = {m.name: m for m in metrics}
    ratio = names["error_time/cbox-original/kdtrace_over_mitsuba_paths_per_second"]
    assert ratio.kind == "ratio" and ratio.value > 0
    assert names["error_time/cbox-original/denoiser_psnr_4spp"].kind == "psnr"
    assert names["error_time/cbox-original/demodulated_denoiser_psnr_4spp"].kind == "psnr"
    assert names["error_time/cbox-original/perceptual_denoiser_display_psnr_4spp"].kind == "psnr"
    assert [m.name for m in read_metrics(out / "metrics" / "error_time.json")] == [m.name for m in metrics]

    csv = pd.read_csv(out / "error_time.csv")
    assert len(csv) == len(METHODS) * 2 and set(csv["method"]) == set(METHODS)
    assert (csv["seconds"] >= csv["render_seconds"]).all() and np.isfinite(csv["psnr"]).all()
    blended = csv[csv["method"] == "kdtrace+denoiser-blend"]
    assert blended["weight"].between(0, 1).all() and np.isfinite(blended["input_psnr"]).all()
    assert names["error_time/cbox-original/blended_denoiser_margin_over_input_db"].kind == "psnr"
    excess = names["error_time/cbox-original/blended_denoiser_flip_excess_over_input"]
    assert excess.kind == "flip" and excess.value == pytest.approx((blended["flip"] - blended["input_flip"]).max())
    mitsuba_denoised = csv[csv["method"].isin(["mitsuba+denoiser", "mitsuba+oidn", "mitsuba+demodulated"])]
    assert (mitsuba_denoised["reconstruction_seconds"] > 0).all() and np.isfinite(mitsuba_denoised["input_psnr"]).all()
    by_method = csv.set_index(["method", "spp"])
    for renderer in ("kdtrace", "mitsuba"):
        plain = f"{renderer}+denoiser"
        for variant in (f"{renderer}+demodulated", f"{renderer}+perceptual"):
            # the same frame as the paper net's pipeline: the same render seconds and input
            assert np.allclose(by_method.loc[variant, "render_seconds"], by_method.loc[plain, "render_seconds"])
            assert np.allclose(by_method.loc[variant, "input_psnr"], by_method.loc[plain, "input_psnr"])
    half = csv[csv["method"] == "kdtrace-half+denoiser+superres"]
    assert (half["paths"] == 16 * 16 * half["spp"]).all() and (half["reconstruction_seconds"] > 0).all()
    markdown = (out / "error_time.md").read_text()
    assert "](error_time/cbox-original.png)" in markdown and "Equal error" in markdown
    assert "smallest of its linear, display and FLIP bounds" in markdown
    assert (out / "error_time" / "cbox-original.png").read_bytes()[:4] == b"\x89PNG"

    row = json.loads((out / "rows" / "error_time" / "cbox-original.json").read_text())
    capsys.readouterr()
    again = generate(config, "tiny", out, progress=False)
    captured = capsys.readouterr()
    assert "cbox-original: reusing the row" in captured.out + captured.err
    assert [m.value for m in again] == [m.value for m in metrics]
    assert json.loads((out / "rows" / "error_time" / "cbox-original.json").read_text()) == row


def test_the_load_note_says_competition_only_when_the_load_exceeds_the_cores(monkeypatch):
    from reports.error_time_present import load_note

    monkeypatch.setattr("os.cpu_count", lambda: 2)
    assert load_note([]) == ""
    quiet = load_note([{"load_average": [1.8, 2.0]}])
    assert "1.8–2.0 on 2 cores" in quiet and "competed" not in quiet
    assert "other processes competed" in load_note([{"load_average": [1.9, 3.1]}])
