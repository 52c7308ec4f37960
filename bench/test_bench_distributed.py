"""Dataset generation on 1 and 2 local Dask workers (group ``distributed``).

Run from the repository root::

    .venv/bin/pytest bench/test_bench_distributed.py --benchmark-enable

One benchmark round generates the quick profile's dataset of ``cbox-original`` (with
``[distributed] scaleout_views`` views) on a 1-worker and then a 2-worker LocalCluster,
each into an empty folder after warming the workers, through
:func:`reports.scaleout.measure_throughput` (the report's own measurement). The views/s
of both and their ratio go into ``extra_info``; afterwards the test checks that both
runs produced the same arrays bit for bit and that the 2-worker run used both workers.
On a shared 2-core machine the ratio depends on the other load (recorded as the load
average before each run); render-bound views approach 2.
"""

from __future__ import annotations

from kdtrace.config import DEFAULT_CONFIG
from reports.scaleout import measure_throughput, throughput_profile

SCENE = "cbox-original"


def test_dataset_throughput_one_and_two_workers(benchmark):
    profile = throughput_profile(DEFAULT_CONFIG.reconstruction.profile("quick"), DEFAULT_CONFIG.distributed.scaleout_views)
    benchmark.group = "distributed"
    result = benchmark.pedantic(measure_throughput, args=(SCENE, profile, (1, 2)), rounds=1, iterations=1)
    one, two = result["runs"]
    benchmark.extra_info.update({
        "views": result["views"], "one_worker_views_per_second": one["views_per_second"],
        "two_worker_views_per_second": two["views_per_second"],
        "two_over_one_worker_throughput": two["views_per_second"] / one["views_per_second"],
        "load_average_before": [run["load_average_before"] for run in result["runs"]],
        "concurrency": [run["concurrency"] for run in result["runs"]],
    })
    print(f"\n{result['views']} views of {SCENE}: 1 worker {one['views_per_second']:.2f} views/s, 2 workers "
          f"{two['views_per_second']:.2f} views/s, ratio {two['views_per_second'] / one['views_per_second']:.2f} "
          f"(concurrency {one['concurrency']:.2f}, {two['concurrency']:.2f}; load average before: "
          f"{one['load_average_before']:.1f}, {two['load_average_before']:.1f})")
    assert result["identical"], "the 1- and 2-worker datasets differ"
    assert one["workers_used"] == 1 and two["workers_used"] == 2
