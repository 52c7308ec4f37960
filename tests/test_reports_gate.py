"""The CI regression gate (reports/gate.py) on synthetic metrics: every failure kind, tolerances,
missing and new metrics, malformed baselines, and the baseline's stable text."""

from __future__ import annotations

import json

import pytest

from kdtrace.config import GateConfig
from kdtrace.provenance import isa_tier
from reports import gate
from reports.metrics import Metric, write_metrics

CONFIG = GateConfig(ratio_tolerance=0.3, ratio_tolerances={"t/*/paired": 0.1}, psnr_tolerance_db=0.1)


def _metrics(*entries: tuple) -> dict[str, Metric]:
    return {name: Metric(name, kind, value) for name, kind, value in entries}


BASELINE = _metrics(
    ("t/a/speed", "ratio", 2.0),
    ("t/a/paired", "ratio", 1.0),
    ("t/a/psnr", "psnr", 30.0),
    ("t/a/refs", "count", 1000),
    ("t/a/unexplained", "zero", 0),
    ("t/a/ztest", "pass", True),
)


def _verdicts(run: dict[str, Metric], baseline: dict[str, Metric] = BASELINE, **kwargs) -> dict[str, gate.Verdict]:
    return {v.name: v for v in gate.compare(baseline, run, CONFIG, **kwargs)}


def _changed(name: str, value) -> dict[str, Metric]:
    run = dict(BASELINE)
    run[name] = Metric(name, BASELINE[name].kind, value)
    return run


def test_identical_run_passes():
    verdicts = _verdicts(dict(BASELINE))
    assert {v.verdict for v in verdicts.values()} == {gate.OK}
    assert "PASSED" in gate.summary(list(verdicts.values()))


@pytest.mark.parametrize(("name", "value", "fails"), [
    ("t/a/speed", 1.41, False),   # -29.5 %: inside the 30 % default
    ("t/a/speed", 1.39, True),    # -30.5 %
    ("t/a/speed", 5.0, False),    # faster never fails
    ("t/a/paired", 0.91, False),  # the override: 10 %
    ("t/a/paired", 0.89, True),
    ("t/a/psnr", 29.91, False),   # -0.09 dB
    ("t/a/psnr", 29.89, True),    # -0.11 dB
    ("t/a/refs", 1001, True),     # counts must match exactly, either way
    ("t/a/refs", 999, True),
    ("t/a/unexplained", 1, True),
    ("t/a/ztest", False, True),
])
def test_each_kind_and_tolerance(name, value, fails):
    verdict = _verdicts(_changed(name, value))[name]
    assert verdict.failed is fails, verdict
    assert verdict.verdict == (gate.FAIL if fails else gate.OK)
    others = [v for n, v in _verdicts(_changed(name, value)).items() if n != name]
    assert not any(v.failed for v in others)


def test_zero_and_pass_fail_without_a_baseline_value():
    # a baseline recorded with a failure does not make the failure acceptable
    baseline = _metrics(("t/a/unexplained", "zero", 3), ("t/a/ztest", "pass", False))
    verdicts = _verdicts(dict(baseline), baseline=baseline)
    assert all(v.failed for v in verdicts.values())
    # and a new metric that fails its absolute rule fails too
    run = dict(BASELINE) | _metrics(("t/b/unexplained", "zero", 2))
    assert _verdicts(run)["t/b/unexplained"].verdict == gate.FAIL


def test_missing_metric_fails_and_new_metric_does_not():
    run = {name: m for name, m in BASELINE.items() if name != "t/a/refs"} | _metrics(("t/b/speed", "ratio", 0.01))
    verdicts = _verdicts(run)
    assert verdicts["t/a/refs"].verdict == gate.MISSING and verdicts["t/a/refs"].failed
    assert verdicts["t/b/speed"].verdict == gate.NEW and not verdicts["t/b/speed"].failed
    ordered = gate.compare(BASELINE, run, CONFIG)
    assert ordered[0].verdict == gate.MISSING  # failures first
    assert "1 missing from the run, 1 new" in gate.summary(ordered) and "FAILED" in gate.summary(ordered)


def test_skipped_scenes_are_not_missing():
    run = {name: m for name, m in BASELINE.items() if name != "t/a/refs"}
    assert _verdicts(run, skip=["*/a/*"])["t/a/speed"].verdict == gate.OK  # present ones still compared
    assert "t/a/refs" not in _verdicts(run, skip=["*/a/*"])


def test_changed_kind_fails():
    run = dict(BASELINE)
    run["t/a/refs"] = Metric("t/a/refs", "ratio", 1000.0)
    verdict = _verdicts(run)["t/a/refs"]
    assert verdict.failed and "kind changed" in verdict.reason


def test_table_has_the_columns_and_reasons():
    text = gate.format_table(gate.compare(BASELINE, _changed("t/a/speed", 1.0), CONFIG))
    header = text.splitlines()[0]
    for column in ("name", "kind", "baseline", "now", "tolerance", "verdict"):
        assert column in header
    assert "FAIL: dropped 50%" in text and ">= 1.4 (-30%)" in text


def test_run_gate_and_update_baseline_round_trip(tmp_path):
    out = tmp_path / "run"
    write_metrics(out, "t", BASELINE.values())
    baseline_file = tmp_path / "baseline.json"
    path, note = gate.update_baseline(out, "quick", baseline=baseline_file)
    assert path == baseline_file and "6 added" in note
    text = baseline_file.read_text()
    assert json.loads(text)["profile"] == "quick"
    # stable: rewriting changes nothing
    assert text == gate.baseline_document("quick", gate.read_baseline(baseline_file), gate.baseline_cpu(baseline_file))
    passed, report = gate.run_gate(out, "quick", CONFIG, baseline=baseline_file)
    assert passed and (out / "gate.md").read_text() == report

    write_metrics(out, "t", _changed("t/a/refs", 1200).values())
    passed, report = gate.run_gate(out, "quick", CONFIG, baseline=baseline_file)
    assert not passed and "changed by +200" in report
    _, note = gate.update_baseline(out, "quick", baseline=baseline_file)
    assert "0 added, 0 removed, 1 changed" in note
    assert gate.run_gate(out, "quick", CONFIG, baseline=baseline_file)[0]


def test_baseline_rounds_floats_to_four_digits(tmp_path):
    path = gate.write_baseline(tmp_path / "b.json", "quick", _metrics(("t/a/speed", "ratio", 0.123456789)))
    assert gate.read_baseline(path)["t/a/speed"].value == 0.1235


@pytest.mark.parametrize(("content", "message"), [
    ("{not json", "not valid JSON"),
    ("[]", "expected an object"),
    ('{"metrics": []}', "expected an object"),
    ('{"metrics": {"t/a": {"kind": "ratio"}}}', "needs exactly"),
    ('{"metrics": {"t/a": {"kind": "ratio", "value": 1, "extra": 2}}}', "needs exactly"),
    ('{"metrics": {"t/a": {"kind": "speed", "value": 1}}}', "is not one of"),
    ('{"metrics": {"t/a": {"kind": "pass", "value": 1}}}', "needs a bool"),
    ('{"metrics": {"t/a": {"kind": "ratio", "value": "fast"}}}', "finite number"),
])
def test_malformed_baseline_is_a_clear_error(tmp_path, content, message):
    path = tmp_path / "baseline.json"
    path.write_text(content)
    with pytest.raises(ValueError, match=message):
        gate.read_baseline(path)


def test_missing_baseline_or_run_says_what_to_do(tmp_path):
    with pytest.raises(FileNotFoundError, match="update-baseline"):
        gate.read_baseline(tmp_path / "none.json")
    with pytest.raises(FileNotFoundError, match="kdtrace report"):
        gate.read_run(tmp_path)


def test_a_name_reported_twice_is_an_error(tmp_path):
    write_metrics(tmp_path, "one", _metrics(("t/a/refs", "count", 1)).values())
    write_metrics(tmp_path, "two", _metrics(("t/a/refs", "count", 1)).values())
    with pytest.raises(ValueError, match="appears twice"):
        gate.read_run(tmp_path)


def test_gate_config_validates_and_matches_overrides():
    assert CONFIG.tolerance_for("t/x/paired") == 0.1 and CONFIG.tolerance_for("t/x/speed") == 0.3
    with pytest.raises(ValueError):
        GateConfig(ratio_tolerance=1.5)
    with pytest.raises(ValueError):
        GateConfig(psnr_tolerance_db=-1.0)


def test_each_machine_kind_gets_its_own_baseline(tmp_path, monkeypatch):
    """Fixed-seed training reproduces on one machine kind only: the gate reads, and update-baseline
    writes, the machine's own PROFILE.SLUG.json once PROFILE.json was recorded on another kind."""
    out = tmp_path / "run"
    write_metrics(out, "t", BASELINE.values())
    monkeypatch.setattr(gate, "BASELINE_DIR", tmp_path)
    monkeypatch.setattr(gate, "cpu_kind", lambda: "Intel(R) Xeon(R) Processor [amx]")
    path, _ = gate.update_baseline(out, "quick")
    assert path == tmp_path / "quick.json" and gate.baseline_cpu(path) == "Intel(R) Xeon(R) Processor [amx]"

    monkeypatch.setattr(gate, "cpu_kind", lambda: "AMD EPYC [avx2]")
    assert gate.baseline_path("quick", cpu="AMD EPYC [avx2]") == tmp_path / "quick.json"  # none of its own yet
    write_metrics(out, "t", _changed("t/a/refs", 1200).values())
    passed, report = gate.run_gate(out, "quick", CONFIG)
    assert not passed and "recorded on Intel(R) Xeon(R) Processor [amx]; this machine: AMD EPYC [avx2]" in report
    path, note = gate.update_baseline(out, "quick")
    assert path == tmp_path / "quick.amd-epyc-avx2.json" and "(new baseline)" in note
    assert gate.read_baseline(tmp_path / "quick.json")["t/a/refs"].value == 1000  # the Xeon one is kept
    assert gate.baseline_path("quick", cpu="AMD EPYC [avx2]") == path
    passed, report = gate.run_gate(out, "quick", CONFIG)
    assert passed and "quick.amd-epyc-avx2.json" in report
    assert gate.cpu_slug("Intel(R) Xeon(R) Processor") == "intel-r-xeon-r-processor"


def test_machine_kind_names_the_vector_tier():
    """Same model name, other ISA: another kind (bf16 training or fp32, other Embree kernels)."""
    assert isa_tier({"avx2", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16"}) == "amx"
    assert isa_tier({"avx2", "avx512f", "avx512_bf16"}) == "avx512-bf16"
    assert isa_tier({"avx2", "avx512f"}) == "avx512"
    assert isa_tier({"sse4_2", "avx2"}) == "avx2"
    assert isa_tier({"sse4_2"}) == isa_tier(set()) == "generic"
    assert gate.cpu_slug("AMD EPYC [avx512-bf16]") == "amd-epyc-avx512-bf16"
