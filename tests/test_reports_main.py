"""The report orchestrator (reports/main.py) with stand-in parts: order, index, provenance, notes,
correctness failures, the gate, and errors for unknown or missing names."""

from __future__ import annotations

import json
import textwrap

import pytest

from kdtrace.cli import main as cli_main
from kdtrace.config import load_config
from reports import gate, main
from reports.metrics import Metric

# A stand-in part: writes a table and a plot, reports a note and a Mitsuba fallback, returns metrics
# whose values come from environment variables so a test can plant a regression.
FAKE_PART = textwrap.dedent('''
    import os
    import warnings
    from pathlib import Path

    from references.llvm import LLVMFallbackWarning
    from reports.metrics import Metric, write_metrics
    from reports.notes import ReportNote

    CALLS = []

    def generate(config, profile_name, out_dir, fresh=False, progress=True):
        CALLS.append((__name__, tuple(config.profile(profile_name).scenes), fresh))
        out_dir = Path(out_dir)
        (out_dir / "fake.md").write_text("# fake")
        (out_dir / "plots").mkdir(exist_ok=True)
        (out_dir / "plots" / "fake.png").write_bytes(b"png")
        warnings.warn("reused 2 of 2 cached rows", ReportNote)
        warnings.warn("Mitsuba llvm_ad_rgb unusable, falling back to scalar_rgb", LLVMFallbackWarning)
        scene = config.profile(profile_name).scenes[0]
        metrics = [Metric(f"fake/{scene}/refs", "count", int(os.environ.get("FAKE_REFS", "100"))),
                   Metric(f"fake/{scene}/unexplained", "zero", int(os.environ.get("FAKE_UNEXPLAINED", "0")))]
        write_metrics(out_dir, "fake", metrics)
        return metrics
''')


@pytest.fixture
def fake_parts(tmp_path, monkeypatch):
    """PARTS replaced by one importable stand-in module; the baseline folder moved to tmp_path."""
    source = tmp_path / "src"
    source.mkdir()
    (source / "fake_report_part.py").write_text(FAKE_PART)
    monkeypatch.syspath_prepend(str(source))
    monkeypatch.setattr(main, "PARTS", {"fake": "fake_report_part", "absent": "no_such_module_for_kdtrace"})
    monkeypatch.setattr(gate, "BASELINE_DIR", tmp_path / "baseline")
    return tmp_path


def test_run_report_writes_index_provenance_and_notes(fake_parts, capsys):
    config = load_config()
    out = fake_parts / "out"
    outcome = main.run_report(config, "quick", out, scenes=["cbox-original", "car"], parts=["fake"], progress=True)
    assert outcome.ok and outcome.gate_passed is None
    (part,) = outcome.parts
    assert part.files == ["fake.md", "metrics/fake.json", "plots/fake.png"]
    assert part.notes == ["reused 2 of 2 cached rows", "Mitsuba llvm_ad_rgb unusable, falling back to scalar_rgb"]
    index = (out / "README.md").read_text()
    assert "[fake.md](fake.md)" in index and "![plots/fake.png](plots/fake.png)" in index
    assert "> **Note:** Mitsuba llvm_ad_rgb unusable, falling back to scalar_rgb" in index
    provenance = json.loads((out / "provenance.json").read_text())
    assert provenance["profile"] == "quick" and provenance["seeds"]["profile"] == config.profile("quick").seed
    assert provenance["machine"]["cpu"] and provenance["machine"]["cores"] >= 1 and provenance["versions"]["numpy"]
    assert provenance["config"]["profiles"]["quick"]["scenes"] == ["cbox-original", "car"]
    assert "note: reused 2 of 2 cached rows" in capsys.readouterr().out
    (out / "older.md").write_text("# from an earlier run")  # listed apart, not under the part that ran
    main.run_report(config, "quick", out, scenes=["car"], parts=["fake"], progress=False)
    index = (out / "README.md").read_text()
    assert index.index("[fake.md]") < index.index("not written by this run") < index.index("[older.md](older.md)")


def test_scene_subset_reaches_the_parts_and_limits_reconstruction_scenes(fake_parts):
    import fake_report_part

    config = load_config()
    main.run_report(config, "quick", fake_parts / "out", scenes=["car", "bunny"], fresh=True, parts=["fake"], progress=False)
    assert fake_report_part.CALLS[-1] == ("fake_report_part", ("car", "bunny"), True)
    limited = main.restrict_scenes(config, "quick", ["car", "bunny"]).profile("quick")
    assert limited.reconstruction_scenes == ("car",)  # only those among the chosen scenes
    assert main.restrict_scenes(config, "quick", None) is config


def test_correctness_failure_and_gate(fake_parts, monkeypatch):
    config = load_config()
    out = fake_parts / "out"
    main.run_report(config, "quick", out, scenes=["car"], parts=["fake"], progress=False)
    gate.update_baseline(out, "quick")
    assert main.run_report(config, "quick", out, scenes=["car"], parts=["fake"], gate=True, progress=False).gate_passed

    monkeypatch.setenv("FAKE_REFS", "150")  # a changed count: the gate fails, the run is not ok
    outcome = main.run_report(config, "quick", out, scenes=["car"], parts=["fake"], gate=True, progress=False)
    assert outcome.gate_passed is False and not outcome.ok and not outcome.correctness_failures
    assert "fake/car/refs" in outcome.gate_text and "changed by +50" in outcome.gate_text
    assert "gate FAILED" in (out / "README.md").read_text()

    monkeypatch.setenv("FAKE_REFS", "100")
    monkeypatch.setenv("FAKE_UNEXPLAINED", "2")  # fails even without the gate
    outcome = main.run_report(config, "quick", out, scenes=["car"], parts=["fake"], progress=False)
    assert not outcome.ok and outcome.correctness_failures == ["fake/car/unexplained: 2 (must be 0)"]


def test_gate_skips_baseline_metrics_of_scenes_left_out(fake_parts):
    config = load_config()
    out = fake_parts / "out"
    gate.write_baseline(gate.baseline_path("quick"), "quick",
                        {"fake/car/refs": Metric("fake/car/refs", "count", 100),
                         "fake/bunny/refs": Metric("fake/bunny/refs", "count", 7)})
    outcome = main.run_report(config, "quick", out, scenes=["car"], parts=["fake"], gate=True, progress=False)
    assert outcome.gate_passed and "fake/bunny/refs" not in outcome.gate_text


def test_unknown_and_missing_names_list_what_exists(fake_parts):
    config = load_config()
    with pytest.raises(ValueError, match=r"without a module: absent \(no_such_module_for_kdtrace\).*--parts fake"):
        main.run_report(config, "quick", fake_parts / "out", progress=False)
    with pytest.raises(ValueError, match="unknown report parts.*known: fake, absent"):
        main.resolve_parts(["nope"])
    with pytest.raises(ValueError, match="unknown scenes.*available:.*cbox-original"):
        main.run_report(config, "quick", fake_parts / "out", scenes=["no-such-scene"], parts=["fake"])
    with pytest.raises(ValueError, match="unknown profile 'huge'; known profiles: paper, quick"):
        main.run_report(config, "huge", fake_parts / "out", parts=["fake"])


def test_cli_gate_and_update_baseline(fake_parts, monkeypatch, capsys):
    out = fake_parts / "out"
    assert cli_main(["report", "--parts", "fake", "--scenes", "car", "--out", str(out)]) == 0
    baselines = fake_parts / "elsewhere"
    assert cli_main(["update-baseline", "--out", str(out), "--baselines", str(baselines)]) == 0
    assert (baselines / "quick.json").is_file()
    assert cli_main(["gate", "--out", str(out), "--baselines", str(baselines)]) == 0
    assert cli_main(["report", "--parts", "fake", "--scenes", "car", "--out", str(out), "--gate"]) == 2  # no baseline yet
    assert "kdtrace update-baseline" in capsys.readouterr().err
    assert cli_main(["update-baseline", "--out", str(out)]) == 0  # the profile's default baseline
    monkeypatch.setenv("FAKE_REFS", "99")
    assert cli_main(["report", "--parts", "fake", "--scenes", "car", "--out", str(out), "--gate"]) == 1
    assert cli_main(["gate", "--out", str(out), "--baselines", str(baselines)]) == 1
    assert "| fake/car/refs" in capsys.readouterr().out
    assert cli_main(["report", "--profile", "huge", "--parts", "fake"]) == 2
    assert "known profiles: paper, quick" in capsys.readouterr().err


def test_table1_and_agreement_end_to_end_with_a_backend_note(tmp_path, monkeypatch):
    """The real first two parts on one small scene; a Mitsuba fallback shows up as a note in the index."""
    import dataclasses
    import warnings

    pytest.importorskip("mitsuba")
    from references import ztest
    from references.llvm import LLVMFallbackWarning

    real_compare = ztest.compare_scene

    def compare_with_fallback(*args, **kwargs):
        warnings.warn("Mitsuba llvm_ad_rgb unusable, falling back to scalar_rgb (test)", LLVMFallbackWarning, stacklevel=2)
        return real_compare(*args, **kwargs)

    monkeypatch.setattr(ztest, "compare_scene", compare_with_fallback)
    config = load_config()
    small = dataclasses.replace(config.profile("quick"), scenes=("cbox-empty",), agreement_rays_per_kind=2000,
                                timing_rays=2000, frame_width=16, frame_height=16, frame_spp=2)
    config = dataclasses.replace(config, profiles={"tiny": small})
    outcome = main.run_report(config, "tiny", tmp_path, parts=["table1", "agreement"], progress=False)
    assert outcome.ok, outcome.correctness_failures
    names = {m.name: m for part in outcome.parts for m in part.metrics}
    assert names["table1/cbox-empty/triangle_references_naive"].value == 12
    assert names["agreement/cbox-empty/unexplained_embree"].value == 0
    assert names["agreement/cbox-empty/mitsuba_ztest"].value is True
    assert "falling back to scalar_rgb (test)" in (tmp_path / "agreement.md").read_text()
    index = (tmp_path / "README.md").read_text()
    assert "> **Note:** Mitsuba llvm_ad_rgb unusable, falling back to scalar_rgb (test)" in index
    assert "[table1.md](table1.md)" in index and "[agreement.md](agreement.md)" in index

    again = main.run_report(config, "tiny", tmp_path, parts=["table1"], progress=False)  # reuses the row
    assert any("reused 1 of 1 scene rows" in note for note in again.parts[0].notes)
