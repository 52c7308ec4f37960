"""scripts/soak.py without soaking: the property list, shards, resuming from records, and the table."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "soak.py"


@pytest.fixture(scope="module")
def soak():
    spec = importlib.util.spec_from_file_location("soak_script", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def fake_record(name: str, examples: int) -> dict:
    return {"property": name, "examples_requested": examples, "passed": True, "passing": examples, "failing": 0,
            "invalid": 3, "wall_seconds": 12.0, "load_before": 0.1, "commit": "abc1234",
            "machine": {"cpu": "test cpu", "cpu_isa": "avx2"}}


def test_properties_are_the_given_tests_in_file_order(soak):
    names = soak.properties()
    source = (SCRIPT.parents[1] / soak.TESTS).read_text()
    assert len(names) >= 10 and len(set(names)) == len(names)
    assert [source.index(f"def {name}(") for name in names] == sorted(source.index(f"def {name}(") for name in names)
    assert all("@given" in source[:source.index(f"def {name}(")].rsplit("\ndef ", 1)[-1] for name in names)


def test_shards_split_the_properties_and_records_are_resumed(soak, tmp_path, capsys):
    names = soak.properties()
    records = tmp_path / "properties"
    records.mkdir()
    for name in names:
        (records / f"{name}.json").write_text(json.dumps(fake_record(name, 7)))
    seen = []
    for shard in ("0/2", "1/2"):
        assert soak.main(["--examples", "7", "--shard", shard, "--out", str(tmp_path)]) == 0
        seen += [line.split(":")[0] for line in capsys.readouterr().out.splitlines() if "soaked before" in line]
    assert sorted(seen) == sorted(names)  # the two shards together are every property, once
    table = (tmp_path / "README.md").read_text()
    assert table.count("| `test_") == len(names) and "test cpu [avx2]" in table


@pytest.mark.parametrize("shard", ["2/2", "1", "a/b", "-1/2"])
def test_a_bad_shard_is_refused(soak, tmp_path, shard):
    with pytest.raises(SystemExit) as stopped:
        soak.main(["--shard", shard, "--out", str(tmp_path)])
    assert stopped.value.code == 2


def test_the_failure_message_keeps_pytests_assertion_lines(soak):
    output = "\n".join(["tests/x.py F", ">   assert bad == 0", "E   AssertionError: ray 3: o=[0, 0, 0]",
                        "E       case=StressScene(...)", "tests/x.py:154: AssertionError", "1 failed"])
    assert soak.failure_message(output) == ["AssertionError: ray 3: o=[0, 0, 0]", "case=StressScene(...)"]
    assert soak.failure_message("1 passed") == []


def test_a_property_past_the_memory_limit_fails_with_a_record_instead_of_being_killed(soak):
    record = soak.soak_one(soak.properties()[0], 1, memory_bytes=200 * 2**20)  # too little to import numba
    assert not record["passed"] and record["returncode"] != 0 and record["memory_limit_bytes"] == 200 * 2**20
    assert record["pytest_tail"]  # pytest's own report of the failure, not an empty record of a killed process


def test_the_failure_message_keeps_the_failing_cases_of_an_exception_group(soak):
    output = "\n".join(["  | MemoryError: Allocation failed", "    | Failing test case: test_x(", "    |     case=S(1),",
                        "    |     seed=3,", "    | )", "    | Explanation:", "=== 1 failed ==="])
    assert soak.failure_message(output) == ["Failing test case: test_x(", "case=S(1),", "seed=3,", ")"]


def test_the_table_says_how_each_property_ended(soak, tmp_path):
    stopped = {**fake_record("test_b", 7), "passed": False, "passing": None, "failing": None, "invalid": None,
               "returncode": 1, "pytest_tail": ["    | MemoryError: Allocation failed (probably too large).", "1 failed"]}
    failed = {**fake_record("test_c", 7), "passed": False, "passing": 5, "failing": 1}
    killed = {**stopped, "property": "test_d", "pytest_tail": [], "returncode": -9}
    table = soak.write_table([fake_record("test_a", 7), stopped, failed, killed], tmp_path).read_text()
    rows = {line.split("|")[1].strip(" `"): line.split("|")[2].strip() for line in table.splitlines() if "`test_" in line}
    assert rows == {"test_a": "passed", "test_b": "stopped (MemoryError)", "test_c": "failed", "test_d": "stopped (exit -9)"}
    assert "| – | – | – |" in table
