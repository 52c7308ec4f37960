"""Plug-in accelerators and denoisers in the benchmarks (``--bench-accelerator`` / ``--bench-denoiser``).

A plug-in is named as :mod:`kdtrace.plugins` accepts it: a short entry-point name
(``brute-force``, ``local``, ``oidn``, ...) or ``package.module:factory``. Both options
may be repeated and take comma-separated lists. In the benchmarks a plug-in appears
as the intersector or method ``plugin:SPEC`` (so ``--bench-accelerator local``, our
own tree through the plug-in path, does not collide with our ``local``), after our
own methods, in the same pytest-benchmark group.

The options are resolved once, in ``bench/conftest.py``'s ``pytest_configure``: an
accelerator's factory is imported (it is called per scene, untimed, by
:meth:`bench._measure.SceneBench.plugin`), a denoiser is loaded outright. Anything
that fails there is a :class:`pytest.UsageError` naming the plug-in.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pytest

from kdtrace.plugins import ACCELERATOR_GROUP, CheckedDenoiser, PluginError, load_denoiser, resolve_factory
from reports.plugins import parse_specs

#: Prefix of a plug-in's intersector / method name in test ids, rows and extra_info.
PLUGIN_PREFIX = "plugin:"


def plugin_name(spec: str) -> str:
    """The benchmark name of the plug-in ``spec``: ``plugin:SPEC``."""
    return PLUGIN_PREFIX + spec


def is_plugin(name: str) -> bool:
    """Whether an intersector / method name is a plug-in's (``plugin:SPEC``)."""
    return name.startswith(PLUGIN_PREFIX)


def plugin_spec(name: str) -> str:
    """The spec of the plug-in name ``plugin:SPEC``."""
    if not is_plugin(name):
        raise ValueError(f"{name!r} is not a plug-in name ({PLUGIN_PREFIX}SPEC)")
    return name[len(PLUGIN_PREFIX):]


@dataclass
class BenchPlugins:
    """The plug-ins of one benchmark run.

    Attributes
    ----------
    accelerators : list of str
        Specs of ``--bench-accelerator``, their factories importable.
    denoisers : dict
        Spec of ``--bench-denoiser`` -> the loaded, validated denoiser.
    """

    accelerators: list[str] = field(default_factory=list)
    denoisers: dict[str, CheckedDenoiser] = field(default_factory=dict)

    @classmethod
    def from_options(cls, accelerators: Iterable[str] | None, denoisers: Iterable[str] | None) -> BenchPlugins:
        """Resolve the options' values.

        Raises
        ------
        pytest.UsageError
            A plug-in cannot be imported, is not registered, is not callable, or (a
            denoiser) its factory raises or returns something that is not callable.
        """
        plugins = cls()
        for option, spec in [("--bench-accelerator", s) for s in parse_specs(accelerators)] + \
                            [("--bench-denoiser", s) for s in parse_specs(denoisers)]:
            try:
                if option == "--bench-accelerator":
                    resolve_factory(spec, ACCELERATOR_GROUP)
                    plugins.accelerators.append(spec)
                else:
                    plugins.denoisers[spec] = load_denoiser(spec)
            except PluginError as error:
                raise pytest.UsageError(f"{option}: {error}") from None
        return plugins

    @property
    def accelerator_names(self) -> list[str]:
        """``plugin:SPEC`` of every accelerator, in option order."""
        return [plugin_name(spec) for spec in self.accelerators]

    @property
    def denoiser_names(self) -> list[str]:
        """``plugin:SPEC`` of every denoiser, in option order."""
        return [plugin_name(spec) for spec in self.denoisers]


#: Where ``bench/conftest.py`` keeps the run's :class:`BenchPlugins`.
PLUGINS_KEY = pytest.StashKey[BenchPlugins]()


def bench_plugins(config: pytest.Config) -> BenchPlugins:
    """The run's :class:`BenchPlugins` (none when ``bench/conftest.py`` did not configure them)."""
    return config.stash.get(PLUGINS_KEY, BenchPlugins())


def jsonable(value: Any) -> Any:
    """``value`` with NumPy scalars and arrays turned into Python numbers and lists (for ``extra_info``)."""
    if isinstance(value, dict):
        return {str(key): jsonable(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [jsonable(item) for item in value]
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    return repr(value)
