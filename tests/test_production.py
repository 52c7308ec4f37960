"""Table 1 at production scale (reports/production.py) on a small generated scene: every stage,
0 wrong against Embree and the float64 oracle, resuming from the stage records, and refusal
before any work when the run would not fit in memory."""

from __future__ import annotations

import dataclasses
import json

import pytest

from kdtrace import resources
from kdtrace.config import DEFAULT_CONFIG
from kdtrace.resources import InsufficientMemoryError
from reports import production

TRIANGLES = 3_000


@pytest.fixture(scope="module")
def small_config():
    """cbox-sphere copies on a small terrain, the quick profile's rays cut down to seconds."""
    quick = DEFAULT_CONFIG.profile("quick")
    tiny = dataclasses.replace(quick, frame_width=48, frame_height=32, frame_spp=1, timing_rays=4_000)
    settings = dataclasses.replace(DEFAULT_CONFIG.production, base_scene="cbox-sphere", triangles=TRIANGLES,
                                   terrain_cells=16, agreement_rays_per_kind=500, oracle_rays=200,
                                   scaling_sizes=(300, 1_000, TRIANGLES))
    return dataclasses.replace(DEFAULT_CONFIG, production=settings, profiles={**DEFAULT_CONFIG.profiles, "tiny": tiny})


@pytest.fixture(scope="module")
def small_run(small_config, tmp_path_factory):
    out = tmp_path_factory.mktemp("production")
    return out, production.generate(small_config, "tiny", out, progress=False)


def test_every_stage_runs_and_nothing_is_wrong(small_run):
    out, records = small_run
    assert list(records) == list(production.STAGES)
    scene = records["scene"]["row"]
    assert scene["triangles"] >= TRIANGLES
    builds = {variant: records[f"build-{variant}"]["row"] for variant in ("naive", "local")}
    assert builds["local"]["triangle_references"] < builds["naive"]["triangle_references"]
    assert all(b["peak_bytes"] >= 0 and b["build_seconds"] > 0 for b in builds.values())
    assert records["embree"]["row"]["commit_seconds"] > 0
    rays = records["rays"]["row"]
    assert all(rays[f"{kind}_mrays_{who}"] > 0 for kind in ("primary", "incoherent", "occlusion")
               for who in ("naive", "local", "embree"))
    agreement = records["agreement"]["row"]
    assert agreement["agreement_rays"] >= 2 * 5 * 500 - 2 * 500  # both trees, every ray kind (primary needs a camera)
    assert agreement["wrong"] == 0 and agreement["unexplained"] == 0
    for variant in ("naive", "local"):
        assert agreement[f"oracle_wrong_{variant}"] == 0 and agreement[f"oracle_unexplained_{variant}"] == 0
        assert agreement[f"oracle_agree_{variant}"] + agreement[f"oracle_ties_{variant}"] == 200
    scaling = records["scaling"]["row"]
    assert [row["triangles"] for row in scaling["rows"]] == [300, 1_000, TRIANGLES]
    table = (out / "table1_production.md").read_text()
    assert f"{scene['triangles']:,} triangles" in table and "| Embree BVH |" in table and "**0**" in table
    assert (out / "table1_build_production.md").is_file() and (out / "figures" / "build_scaling_production.png").is_file()
    summary = json.loads((out / "table1_production.json").read_text())
    assert summary["config"]["production"]["triangles"] == TRIANGLES and "machine" in summary


def test_a_second_run_resumes_from_the_stage_records(small_run, small_config, monkeypatch):
    out, records = small_run

    def measuring(self, stage):
        raise AssertionError(f"stage {stage} was measured again")

    monkeypatch.setattr(production.Run, "stage", measuring)
    again = production.generate(small_config, "tiny", out, progress=False)
    assert {stage: record["measured_at"] for stage, record in again.items()} == \
        {stage: record["measured_at"] for stage, record in records.items()}


def test_a_changed_setting_measures_again(small_config):
    changed = dataclasses.replace(small_config, production=dataclasses.replace(small_config.production, seed=7))
    assert production.stage_key(changed, "tiny", "rays") != production.stage_key(small_config, "tiny", "rays")


def test_a_run_that_does_not_fit_is_refused_before_any_work(small_config, tmp_path, monkeypatch):
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemAvailable:    2097152 kB\n")  # 2 GiB
    monkeypatch.setattr(resources, "MEMINFO", meminfo)
    big = dataclasses.replace(small_config, production=dataclasses.replace(small_config.production,
                                                                            triangles=10_000_000))
    with pytest.raises(InsufficientMemoryError, match=r"10,000,000 triangles.*lower \[production\] triangles"):
        production.generate(big, "tiny", tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()
