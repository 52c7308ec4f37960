"""Renderer throughput against Mitsuba (``reports/throughput.py``): files, metrics, the image check, reuse."""

from __future__ import annotations

import dataclasses

import pandas as pd
import pytest

from kdtrace.config import ProfileConfig, load_config
from kdtrace.timing import alternating_seconds
from reports import throughput
from reports.metrics import read_metrics


@pytest.fixture
def small_frames(monkeypatch):
    """32x32 frames at 2 spp and 2 rounds: seconds, not minutes."""
    monkeypatch.setattr(throughput, "SIZE", 32)
    monkeypatch.setattr(throughput, "SPP", 2)
    monkeypatch.setattr(throughput, "ROUNDS", 2)
    monkeypatch.setattr(throughput, "PAUSE_SECONDS", 0.0)


def tiny_config():
    config = load_config()
    profile = ProfileConfig(scenes=("cbox-original",), reconstruction_scenes=("cbox-original",))
    return dataclasses.replace(config, profiles={"tiny": profile})


def test_alternating_rounds_take_turns():
    calls = []
    ours, theirs = _recorder(calls, "ours", 1.0), _recorder(calls, "theirs", 2.0)
    their_seconds, ours_seconds = alternating_seconds(theirs, ours, 3)
    assert calls == ["theirs", "ours", "ours", "theirs", "theirs", "ours"]
    assert ours_seconds == [1.0] * 3 and their_seconds == [2.0] * 3


def _recorder(calls: list, name: str, seconds: float):
    def run() -> float:
        calls.append(name)
        return seconds
    return run


def test_generate_writes_ratios_and_checks_the_images(shared_scenes, isolated_cache, small_frames, tmp_path, capsys):
    pytest.importorskip("mitsuba")
    config, out = tiny_config(), tmp_path / "report"
    metrics = throughput.generate(config, "tiny", out, progress=False)
    names = {m.name: m for m in metrics}
    for depth in throughput.DEPTHS:
        ratio = names[f"throughput/cbox-original/max_depth_{depth}_kdtrace_over_mitsuba_paths_per_second"]
        assert ratio.kind == "ratio" and ratio.value > 0
        mismatch = names[f"throughput/cbox-original/max_depth_{depth}_mean_radiance_mismatch"]
        assert mismatch.kind == "zero" and mismatch.value == 0  # both renderers estimate the same image
    assert [m.name for m in read_metrics(out / "metrics" / "throughput.json")] == [m.name for m in metrics]
    table = pd.read_csv(out / "throughput.csv")
    assert list(table["max_depth"]) == list(throughput.DEPTHS)
    assert set(table["met"]) <= {"yes", "no"} and (table["target"] == [throughput.TARGETS[d] for d in throughput.DEPTHS]).all()
    assert "ours / Mitsuba" in (out / "throughput.md").read_text()
    assert (out / "throughput.provenance.json").exists()

    # A second run reuses the cached row (same renderer, same settings) and says so.
    capsys.readouterr()
    again = throughput.generate(config, "tiny", out, progress=True)
    captured = capsys.readouterr()
    assert "reusing the row" in captured.out + captured.err
    assert [m.value for m in again] == [m.value for m in metrics]


def test_a_renderer_that_estimates_another_image_fails_the_check(shared_scenes, isolated_cache, small_frames,
                                                                  tmp_path, monkeypatch):
    """Not vacuous: Mitsuba's frame scaled by 2 must show as a mismatch."""
    pytest.importorskip("mitsuba")
    image = throughput.MitsubaTimer.image
    monkeypatch.setattr(throughput.MitsubaTimer, "image", lambda self, spp, seed: 2.0 * image(self, spp, seed))
    with pytest.warns(UserWarning, match="mean radiances differ"):
        metrics = throughput.generate(tiny_config(), "tiny", tmp_path / "report", progress=False)
    assert {m.name: m.value for m in metrics}["throughput/cbox-original/max_depth_3_mean_radiance_mismatch"] == 1
