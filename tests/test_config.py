"""The configuration dataclasses against ``kdtrace/defaults.toml``."""

from __future__ import annotations

import dataclasses

import pytest

from kdtrace.config import (
    CacheConfig,
    DistributedConfig,
    EmbreeCheckConfig,
    KDTreeConfig,
    RenderConfig,
    load_config,
)


@pytest.mark.parametrize("section, cls", [("kdtree", KDTreeConfig), ("cache", CacheConfig),
                                          ("embree_check", EmbreeCheckConfig), ("render", RenderConfig),
                                          ("distributed", DistributedConfig)])
def test_dataclass_defaults_are_the_shipped_defaults(section, cls):
    """``KDTreeConfig(min_leaf_size=1)`` and the like (tests, user code) must fill the fields they
    leave out with what ``defaults.toml`` ships, or a change of a default there silently stops
    reaching them (a changed leaf size once had to be changed in two places)."""
    shipped = getattr(load_config(), section)
    bare = cls()
    differing = {field.name: (getattr(bare, field.name), getattr(shipped, field.name))
                 for field in dataclasses.fields(cls) if getattr(bare, field.name) != getattr(shipped, field.name)}
    assert not differing, f"[{section}] dataclass default != defaults.toml: {differing}"
