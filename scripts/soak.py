"""Soak every hypothesis property of tests/test_kdtree_stress.py, one after another, resumably.

Each property runs in its own pytest process with ``KDTRACE_SOAK_EXAMPLES`` examples (default
10,000); its outcome (examples passing, failing, invalid, seconds, the load average before and
after, commit, machine) is written to ``results/soak/properties/NAME.json`` (``--out``) as soon as it ends,
and the table ``results/soak/README.md`` is rewritten from every record. A property whose
record was made with the same example count is skipped, so a soak can span sittings: run the
command again and it goes on with the next property. Run it on an idle machine; on two cores,
two shards (``--shard 0/2`` and ``--shard 1/2``, each with ``NUMBA_NUM_THREADS=1``) soak
every other property side by side.

Usage::

    .venv/bin/python scripts/soak.py [--examples N] [-k PATTERN] [--shard I/N] [--again] [--memory-gb G] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

REPOSITORY = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPOSITORY))

from kdtrace.cache import atomic_write_bytes  # noqa: E402
from kdtrace.provenance import stamp  # noqa: E402

TESTS = "tests/test_kdtree_stress.py"
RESULTS = REPOSITORY / "results" / "soak"
#: hypothesis's statistics line of one phase, e.g. "10000 passing, 0 failing, and 271 invalid test cases".
_COUNTS = re.compile(r"(\d+) passing, (\d+) failing, and (\d+) invalid")
_SECONDS = re.compile(r"during generate phase \(([\d.]+) seconds\)")


def properties() -> list[str]:
    """The names of the file's hypothesis properties (tests with ``@given``), in file order."""
    source = (REPOSITORY / TESTS).read_text().splitlines()
    names, pending = [], False
    for line in source:
        pending = pending or line.startswith("@given")
        found = re.match(r"def (test_\w+)\(", line)
        if found:
            if pending:
                names.append(found.group(1))
            pending = False
    return names


def soak_one(name: str, examples: int, memory_bytes: int | None = None) -> dict:
    """Run one property with ``examples`` examples; its record (see the module docstring).

    ``memory_bytes`` caps the pytest process's address space (``RLIMIT_AS``), so that an example
    that runs away with memory fails with a MemoryError that names it instead of being killed by
    the kernel with the machine's memory (and the record's output) gone.
    """
    load_before = os.getloadavg()[0]
    # the code soaked is the code at the start: commits made while it runs are not in the record's commit
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPOSITORY, capture_output=True,
                            text=True).stdout.strip()
    started = time.perf_counter()
    completed = subprocess.run(
        [sys.executable, "-m", "pytest", f"{TESTS}::{name}", "-m", "slow or not slow", "-p", "no:cacheprovider",
         "-q", "--hypothesis-show-statistics"],
        cwd=REPOSITORY, env={**os.environ, "KDTRACE_SOAK_EXAMPLES": str(examples)}, capture_output=True, text=True,
        preexec_fn=None if memory_bytes is None else lambda: resource.setrlimit(resource.RLIMIT_AS, (memory_bytes,) * 2))
    seconds = time.perf_counter() - started
    output = completed.stdout + completed.stderr
    counts = _COUNTS.search(output)
    generate = _SECONDS.search(output)
    return {
        "property": name, "examples_requested": examples, "passed": completed.returncode == 0,
        "returncode": completed.returncode, "memory_limit_bytes": memory_bytes,
        "passing": int(counts.group(1)) if counts else None, "failing": int(counts.group(2)) if counts else None,
        "invalid": int(counts.group(3)) if counts else None,
        "generate_seconds": float(generate.group(1)) if generate else None, "wall_seconds": round(seconds, 1),
        "load_before": load_before, "load_after": os.getloadavg()[0],
        "commit": commit,
        "failure": failure_message(output), "pytest_tail": output.strip().splitlines()[-15:], **stamp({}),
    }


def failure_message(output: str, lines: int = 40) -> list[str]:
    """The first ``lines`` lines of pytest's ``E`` lines (the assertion and the falsifying example) and of
    hypothesis's failing test cases (``Failing test case: ...`` up to its closing parenthesis), or []."""
    kept, in_case = [], False
    for line in output.splitlines():
        text = line.lstrip(" |")
        in_case = in_case or text.startswith("Failing test case:")
        if line.startswith("E ") or in_case:
            kept.append(line[1:].strip() if line.startswith("E ") else text.strip())
        in_case = in_case and text.rstrip() != ")"
    return kept[:lines]


def outcome(record: dict) -> str:
    """``passed``, ``failed`` (hypothesis found failing examples) or ``stopped`` (the run ended before
    hypothesis's statistics, e.g. by a MemoryError or a signal), with the exception's name where known."""
    if record["passed"]:
        return "passed"
    if record["failing"]:
        return "failed"
    error = next((line.split(":")[0].split()[-1] for line in reversed(record.get("pytest_tail", []))
                  if re.search(r"\w+Error\b|\w+Exception\b", line.split(":")[0])), None)
    return f"stopped ({error})" if error else f"stopped (exit {record.get('returncode', '?')})"


def _count(value) -> str:
    return "–" if value is None else str(value)


def write_table(records: list[dict], out: Path) -> Path:
    """``OUT/README.md``: one row per soaked property."""
    lines = ["# Soak of the KD-tree properties", "",
             f"`.venv/bin/python scripts/soak.py`: every hypothesis property of `{TESTS}`, one pytest process each. "
             "Each example builds both trees on a drawn scene and checks its rays against the float64 oracle and the "
             "wrong/unexplained classifier. Seconds depend on the load: two shards side by side (`--shard`) put it "
             "near 2 and give each property one numba thread. One record per property in [properties/](properties/).",
             "",
             "| property | outcome | examples passing | failing | invalid (filtered) | seconds | load before | "
             "numba threads | commit | machine |",
             "|---|---|---:|---:|---:|---:|---:|---:|---|---|"]
    for record in records:
        machine = record.get("machine", {})
        lines.append(f"| `{record['property']}` | {outcome(record)} | {_count(record['passing'])} | "
                     f"{_count(record['failing'])} | {_count(record['invalid'])} | "
                     f"{record['wall_seconds']:.0f} | {record['load_before']:.2f} | {machine.get('numba_threads', '?')} | "
                     f"{record['commit']} | {machine.get('cpu', '?')} [{machine.get('cpu_isa', '?')}] |")
    return atomic_write_bytes(out / "README.md", ("\n".join(lines) + "\n").encode())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--examples", type=int, default=int(os.environ.get("KDTRACE_SOAK_EXAMPLES", "10000")))
    parser.add_argument("-k", dest="pattern", default="", help="only properties whose name contains this")
    parser.add_argument("--shard", default="0/1", metavar="I/N",
                        help="only every N-th property, starting with the I-th (0-based), of those selected")
    parser.add_argument("--memory-gb", type=float, default=8.0,
                        help="address-space limit of each property's process, GiB (0: none)")
    parser.add_argument("--again", action="store_true", help="soak properties that already have a record")
    parser.add_argument("--out", type=Path, default=RESULTS, help="folder of the records and table (results/soak)")
    args = parser.parse_args(argv)
    if args.examples < 1:
        parser.error("--examples must be at least 1")
    shard = re.fullmatch(r"(\d+)/(\d+)", args.shard)
    if not shard or not int(shard.group(1)) < int(shard.group(2)):
        parser.error(f"--shard takes I/N with 0 <= I < N, got {args.shard!r}")
    names = [name for name in properties() if args.pattern in name]
    if not names:
        parser.error(f"no property of {TESTS} contains {args.pattern!r}")
    names = names[int(shard.group(1))::int(shard.group(2))]
    failed = 0
    for name in names:
        path = args.out / "properties" / f"{name}.json"
        if path.is_file() and not args.again:
            record = json.loads(path.read_text())
            if record.get("examples_requested") == args.examples:
                print(f"{name}: soaked before ({record['passing']} passing, {record['failing']} failing), skipped")
                continue
        print(f"{name}: {args.examples} examples ...", flush=True)
        record = soak_one(name, args.examples, int(args.memory_gb * 2**30) if args.memory_gb else None)
        atomic_write_bytes(path, json.dumps(record, indent=1).encode())
        failed += not record["passed"]
        print(f"{name}: {record['passing']} passing, {record['failing']} failing, {record['wall_seconds']:.0f} s",
              flush=True)
        rewrite_table(args.out)  # after every property: a soak stopped midway still has its table
    print(f"wrote {rewrite_table(args.out)}")
    return 1 if failed else 0


def rewrite_table(out: Path) -> Path:
    """``OUT/README.md`` from every record in ``OUT/properties``, in the file's order of the properties."""
    records = [json.loads(p.read_text()) for p in sorted((out / "properties").glob("*.json"))]
    order = {name: i for i, name in enumerate(properties())}
    return write_table(sorted(records, key=lambda r: order.get(r["property"], len(order))), out)


if __name__ == "__main__":
    sys.exit(main())
