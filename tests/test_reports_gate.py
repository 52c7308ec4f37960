"""The CI regression gate (reports/gate.py) on synthetic metrics: every failure kind, tolerances,
missing and new metrics, malformed baselines, and the baseline's stable text."""

from __future__ import annotations

import json

import pytest

from kdtrace.config import GateConfig
from kdtrace.provenance import isa_tier
from reports import gate
from reports.metrics import Metric, write_metrics

CONFIG = GateConfig(ratio_tolerance=0.3, ratio_tolerances={"t/*/paired": 0.1}, psnr_tolerance_db=0.1, flip_tolerance=0.002)


def _metrics(*entries: tuple) -> dict[str, Metric]:
    return {name: Metric(name, kind, value) for name, kind, value in entries}


BASELINE = _metrics(
    ("t/a/speed", "ratio", 2.0),
    ("t/a/paired", "ratio", 1.0),
    ("t/a/psnr", "psnr", 30.0),
    ("t/a/flip", "flip", 0.05),
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
    ("t/a/flip", 0.0519, False),  # +0.0019: inside the default +0.002
    ("t/a/flip", 0.0521, True),
    ("t/a/flip", 0.01, False),    # lower is better
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
    assert verdict.failed and verdict.reason == "kind changed from count to ratio"


def test_table_has_the_columns_and_reasons():
    text = gate.format_table(gate.compare(BASELINE, _changed("t/a/speed", 1.0), CONFIG))
    header = text.splitlines()[0]
    for column in ("name", "kind", "baseline", "now", "tolerance", "verdict"):
        assert column in header
    assert "FAIL: dropped 50%" in text and ">= 1.4 (-30%)" in text


XEON, EPYC_AVX2 = "Intel(R) Xeon(R) Processor [avx512-bf16]", "AMD EPYC [avx2]"


@pytest.fixture
def on_kind(monkeypatch):
    """Set the machine kind the gate sees; returns the setter."""
    def set_kind(kind: str) -> None:
        monkeypatch.setattr(gate, "cpu_kind", lambda: kind)
    set_kind(XEON)
    return set_kind


def test_run_gate_and_update_baseline_round_trip(tmp_path, on_kind):
    out = tmp_path / "run"
    write_metrics(out, "t", BASELINE.values())
    paths, note = gate.update_baseline(out, "quick", directory=tmp_path)
    shared, ratios = tmp_path / "quick.json", tmp_path / "quick.ratios.intel-r-xeon-r-processor-avx512-bf16.json"
    assert paths == [shared, ratios] and "5 added" in note and "2 added" in note
    # the deterministic metrics in the shared file, the speed ratios in the kind's own
    assert {m.kind for m in gate.read_baseline(shared).values()} == {"psnr", "flip", "count", "zero", "pass"}
    assert set(gate.read_baseline(ratios)) == {"t/a/speed", "t/a/paired"} and gate.baseline_cpu(ratios) == XEON
    text = shared.read_text()
    assert json.loads(text)["profile"] == "quick" and "cpu" not in json.loads(text)
    # stable: rewriting changes nothing
    assert text == gate.baseline_document("quick", gate.read_baseline(shared))
    passed, report = gate.run_gate(out, "quick", CONFIG, directory=tmp_path)
    assert passed and (out / "gate.md").read_text() == report
    assert "recorded on this machine kind (Intel(R) Xeon(R) Processor [avx512-bf16])" in report

    write_metrics(out, "t", _changed("t/a/refs", 1200).values())
    passed, report = gate.run_gate(out, "quick", CONFIG, directory=tmp_path)
    assert not passed and "changed by +200" in report
    _, note = gate.update_baseline(out, "quick", directory=tmp_path)
    assert "0 added, 0 removed, 1 changed" in note
    assert gate.run_gate(out, "quick", CONFIG, directory=tmp_path)[0]


def test_a_planted_regression_in_a_count_a_psnr_and_a_ratio_each_fails_the_gate(tmp_path, on_kind):
    out = tmp_path / "run"
    write_metrics(out, "t", BASELINE.values())
    gate.update_baseline(out, "quick", directory=tmp_path)
    for name, value, reason in (("t/a/refs", 999, "changed by -1"), ("t/a/psnr", 29.5, "dropped 0.50 dB"),
                                ("t/a/flip", 0.06, "rose +0.0100"), ("t/a/speed", 1.0, "dropped 50%")):
        write_metrics(out, "t", _changed(name, value).values())
        passed, report = gate.run_gate(out, "quick", CONFIG, directory=tmp_path)
        assert not passed and f"FAIL: {reason}" in report and "1 failed" in report


def test_every_kind_reads_one_deterministic_baseline_and_only_its_own_ratios(tmp_path, on_kind):
    """A count recorded on one kind is gated on every kind; a kind with no ratios of its own gates
    the deterministic metrics and says why its ratios were not gated."""
    out = tmp_path / "run"
    write_metrics(out, "t", BASELINE.values())
    gate.update_baseline(out, "quick", directory=tmp_path)

    on_kind(EPYC_AVX2)
    passed, report = gate.run_gate(out, "quick", CONFIG, directory=tmp_path)
    assert passed and "speed ratios **not gated**: no speed-ratio baseline for this machine kind (AMD EPYC [avx2])" in report
    assert "kinds with one: Intel(R) Xeon(R) Processor [avx512-bf16]" in report and "2 not gated" in report
    assert "| t/a/speed " in report and "not gated" in report
    # a slower ratio is not judged here, a changed count is
    write_metrics(out, "t", _changed("t/a/speed", 0.1).values())
    assert gate.run_gate(out, "quick", CONFIG, directory=tmp_path)[0]
    write_metrics(out, "t", _changed("t/a/refs", 1001).values())
    assert not gate.run_gate(out, "quick", CONFIG, directory=tmp_path)[0]
    # recording this kind's ratios leaves the shared file and the other kind's ratios as they were
    write_metrics(out, "t", _changed("t/a/speed", 3.0).values())
    xeon_ratios = (tmp_path / "quick.ratios.intel-r-xeon-r-processor-avx512-bf16.json").read_text()
    paths, note = gate.update_baseline(out, "quick", directory=tmp_path)
    assert paths[1] == tmp_path / "quick.ratios.amd-epyc-avx2.json" and "(new baseline)" in note
    assert "quick.json: 5 metrics; 0 added, 0 removed, 0 changed" in note
    assert (tmp_path / "quick.ratios.intel-r-xeon-r-processor-avx512-bf16.json").read_text() == xeon_ratios
    passed, report = gate.run_gate(out, "quick", CONFIG, directory=tmp_path)
    assert passed and "quick.ratios.amd-epyc-avx2.json" in report and "0 not gated" in report


def test_baselines_recorded_for_another_profile_kind_or_machine_are_refused(tmp_path, on_kind):
    out = tmp_path / "run"
    write_metrics(out, "t", BASELINE.values())
    gate.update_baseline(out, "quick", directory=tmp_path)
    with pytest.raises(ValueError, match=r"quick\.json was recorded for profile 'quick', not 'standard'"):
        gate.read_baseline(tmp_path / "quick.json", "standard")
    ratio_file = tmp_path / "quick.ratios.intel-r-xeon-r-processor-avx512-bf16.json"
    with pytest.raises(ValueError, match="does not belong in the machine-independent baseline"):
        gate.read_baseline(ratio_file, "quick", machine_dependent=False)
    with pytest.raises(ValueError, match="does not belong in a per-machine-kind ratio file"):
        gate.read_baseline(tmp_path / "quick.json", "quick", machine_dependent=True)
    document = json.loads(ratio_file.read_text())
    ratio_file.write_text(json.dumps({**document, "cpu": EPYC_AVX2}))
    with pytest.raises(ValueError, match="recorded on 'AMD EPYC \\[avx2\\]', not on this machine kind"):
        gate.run_gate(out, "quick", CONFIG, directory=tmp_path)
    (tmp_path / "quick.json").unlink()
    with pytest.raises(FileNotFoundError, match="quick.json"):
        gate.run_gate(out, "quick", CONFIG, directory=tmp_path)


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


def test_machine_kind_names_the_vector_tier():
    """Same model name, other ISA: another kind (bf16 training or fp32, other Embree kernels)."""
    assert isa_tier({"avx2", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16"}) == "amx"
    assert isa_tier({"avx2", "avx512f", "avx512_bf16"}) == "avx512-bf16"
    assert isa_tier({"avx2", "avx512f"}) == "avx512"
    assert isa_tier({"sse4_2", "avx2"}) == "avx2"
    assert isa_tier({"sse4_2"}) == isa_tier(set()) == "generic"
    assert gate.cpu_slug("AMD EPYC [avx512-bf16]") == "amd-epyc-avx512-bf16"
