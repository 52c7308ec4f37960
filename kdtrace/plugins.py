"""Third-party acceleration structures and denoisers ("bring your own method").

A plug-in is named by a *spec*: ``package.module:factory`` (imported directly), or
a short name registered by an installed package under the entry-point group
:data:`ACCELERATOR_GROUP` or :data:`DENOISER_GROUP`. Our own methods are registered
the same way in kdtrace's ``pyproject.toml`` (accelerators ``local``, ``naive``,
``embree``; denoiser ``oidn``), so there is one loading path, not two.

- An accelerator factory is ``make(scene) -> Accelerator``.
- A denoiser factory is ``make() -> Denoiser``.

:func:`load_accelerator` and :func:`load_denoiser` wrap what the factory returns
so every answer is checked: a plug-in that raises, or returns the wrong shape or
dtype (floats must be float32 or float64), NaN, an infinite barycentric or a miss
whose ``t`` is not ``+inf``, a triangle index out of range, or ``stats`` that are not a
mapping, raises :class:`PluginError` naming the plug-in's spec and what it returned.
Valid answers are handed on C-contiguous and in native byte order.
"""

from __future__ import annotations

import importlib
import importlib.metadata
from collections.abc import Callable, Mapping
from typing import Protocol, runtime_checkable

import numpy as np

from kdtrace.scene import Scene

#: Entry-point group of accelerator factories ``make(scene)``.
ACCELERATOR_GROUP = "kdtrace.accelerators"
#: Entry-point group of denoiser factories ``make()``.
DENOISER_GROUP = "kdtrace.denoisers"
#: Our KD-trees' short names: what ``kdtrace check-embree`` compares when no accelerator is named.
OUR_ACCELERATORS = ("local", "naive")


class PluginError(ValueError):
    """A plug-in could not be loaded, raised, or returned an invalid answer (the CLI exits with status 2)."""


@runtime_checkable
class Accelerator(Protocol):
    """What an accelerator factory returns: the two queries of :class:`kdtrace.kdtree.KDTree`.

    An optional ``stats`` dict (``references``, ``bytes``, ``nodes``,
    ``build_seconds``) fills the Table 1 columns it knows.
    """

    def intersect(
        self, origins: np.ndarray, directions: np.ndarray, tmin: float = 0.0, tmax: float | np.ndarray = np.inf
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Closest hit of every ray ``o + t d`` with ``tmin < t < tmax``.

        Parameters
        ----------
        origins, directions : (N, 3) float arrays
            Rays in scene units; directions need not be unit.
        tmin, tmax : float or (N,) array
            Accepted range of ``t``, in units of ``|d|``.

        Returns
        -------
        t : (N,) float64 (float32 accepted), inf on a miss
        tri : (N,) int, row of ``scene.triangles``, -1 on a miss
        u, v : (N,) float64 (float32 accepted), barycentric weights of vertices 1 and 2
        """

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tmax: float | np.ndarray) -> np.ndarray:
        """(N,) bool: whether anything is hit with ``0 < t < tmax`` (units of ``|d|``)."""


@runtime_checkable
class Denoiser(Protocol):
    """What a denoiser factory returns: ``fn(color, albedo, normal)``.

    All three inputs and the output are float32 ``(H, W, 3)`` linear images:
    radiance (output likewise), albedo in [0, 1], normals in [-1, 1].
    """

    def __call__(self, color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray: ...


def entry_points(group: str) -> importlib.metadata.EntryPoints:
    """The installed entry points of ``group`` (the one lookup, so tests can replace it)."""
    return importlib.metadata.entry_points(group=group)


def resolve_factory(spec: str, group: str) -> Callable:
    """The factory a spec names: ``package.module:attribute`` or a short name in ``group``.

    Raises
    ------
    PluginError
        The module, attribute or entry point does not exist or is not callable.
    """
    if ":" in spec:
        module_name, _, attribute = spec.partition(":")
        try:
            factory = importlib.import_module(module_name)
            for part in attribute.split("."):
                factory = getattr(factory, part)
        except (ImportError, AttributeError) as error:
            raise PluginError(f"plug-in {spec!r}: cannot import it ({type(error).__name__}: {error})") from error
    else:
        found = {point.name: point for point in entry_points(group)}
        if spec not in found:
            raise PluginError(f"plug-in {spec!r}: no such name in entry-point group {group!r}; "
                              f"installed: {', '.join(sorted(found)) or 'none'} (or give package.module:factory)")
        try:
            factory = found[spec].load()
        except Exception as error:
            raise PluginError(f"plug-in {spec!r}: loading {found[spec].value} failed ({type(error).__name__}: {error})") from error
    if not callable(factory):
        raise PluginError(f"plug-in {spec!r}: {type(factory).__name__} is not callable")
    return factory


def _call(spec: str, what: str, fn: Callable, *args, **kwargs):
    """``fn(*args, **kwargs)``, with any exception re-raised as a :class:`PluginError` naming the plug-in."""
    try:
        return fn(*args, **kwargs)
    except Exception as error:
        raise PluginError(f"plug-in {spec!r}: {what} raised {type(error).__name__}: {error}") from error


def _describe(value) -> str:
    if isinstance(value, np.ndarray):
        return f"array of shape {value.shape}, dtype {value.dtype}"
    return type(value).__name__


def _check_array(spec: str, what: str, value, shape: tuple[int, ...], kinds: str, kind_name: str) -> np.ndarray:
    """``value`` if it is an ndarray of ``shape`` whose dtype kind is in ``kinds``, else a PluginError.

    Floats must be float32 or float64. The array is handed on C-contiguous and in native
    byte order (a copy when it was strided or big-endian).
    """
    if not isinstance(value, np.ndarray) or value.shape != shape or value.dtype.kind not in kinds:
        raise PluginError(f"plug-in {spec!r}: {what} must be a {kind_name} array of shape {shape}, got {_describe(value)}")
    if value.dtype.kind == "f" and value.dtype.itemsize not in (4, 8):
        raise PluginError(f"plug-in {spec!r}: {what} must be a float32 or float64 array, got {_describe(value)}")
    return np.ascontiguousarray(value, dtype=value.dtype.newbyteorder("="))


class CheckedAccelerator:
    """An accelerator whose every answer is validated (see :func:`load_accelerator`).

    Attributes
    ----------
    spec : str
        The plug-in's spec string, used in every error.
    inner : Accelerator
        What the factory returned.
    stats : dict
        The plug-in's ``stats``, or empty.
    """

    def __init__(self, spec: str, inner: Accelerator, n_triangles: int) -> None:
        if not isinstance(inner, Accelerator):
            raise PluginError(f"plug-in {spec!r}: the factory returned a {type(inner).__name__}, "
                              "which has no intersect and occluded methods")
        self.spec = spec
        self.inner = inner
        self.n_triangles = n_triangles
        stats = getattr(inner, "stats", None)
        if stats is not None and not isinstance(stats, Mapping):
            raise PluginError(f"plug-in {spec!r}: stats must be a dict, got {type(stats).__name__}")
        self.stats = dict(stats or {})

    def __repr__(self) -> str:
        return f"CheckedAccelerator({self.spec!r})"

    def intersect(self, origins, directions, tmin=0.0, tmax=np.inf):
        """:meth:`Accelerator.intersect` of the plug-in, validated; arguments and returns as there."""
        n = len(origins)
        answer = _call(self.spec, "intersect", self.inner.intersect, origins, directions, tmin, tmax)
        if not isinstance(answer, tuple) or len(answer) != 4:
            raise PluginError(f"plug-in {self.spec!r}: intersect must return a tuple (t, tri, u, v), got {_describe(answer)}"
                              + (f" of length {len(answer)}" if isinstance(answer, tuple) else ""))
        t, tri, u, v = (_check_array(self.spec, f"intersect's {name}", value, (n,), kinds, kind_name)
                        for name, value, kinds, kind_name in (("t", answer[0], "f", "float"), ("tri", answer[1], "iu", "integer"),
                                                              ("u", answer[2], "f", "float"), ("v", answer[3], "f", "float")))
        hit = tri >= 0
        bad = (tri < -1) | (tri >= self.n_triangles)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise PluginError(f"plug-in {self.spec!r}: intersect returned tri[{i}] = {int(tri[i])}, "
                              f"outside [-1, {self.n_triangles}) for a scene of {self.n_triangles} triangles")
        for name, bad in (("t", np.isnan(t)), ("u", hit & ~np.isfinite(u)), ("v", hit & ~np.isfinite(v))):
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                value = {"t": t, "u": u, "v": v}[name][i]
                raise PluginError(f"plug-in {self.spec!r}: intersect returned {name}[{i}] = {'NaN' if np.isnan(value) else value} "
                                  f"(tri[{i}] = {int(tri[i])})")
        wrong_t = (np.isfinite(t) != hit) | (~hit & (t != np.inf))
        if wrong_t.any():
            i = int(np.flatnonzero(wrong_t)[0])
            raise PluginError(f"plug-in {self.spec!r}: intersect returned t[{i}] = {t[i]} with tri[{i}] = {int(tri[i])}; "
                              "a hit needs a finite t, a miss t = inf and tri = -1")
        return t, tri, u, v

    def occluded(self, origins, directions, tmax):
        """:meth:`Accelerator.occluded` of the plug-in, validated."""
        answer = _call(self.spec, "occluded", self.inner.occluded, origins, directions, tmax)
        return _check_array(self.spec, "occluded's answer", answer, (len(origins),), "b", "bool")


class CheckedDenoiser:
    """A denoiser whose every output is validated (see :func:`load_denoiser`)."""

    def __init__(self, spec: str, inner: Denoiser) -> None:
        if not callable(inner):
            raise PluginError(f"plug-in {spec!r}: the factory returned a {type(inner).__name__}, which is not callable")
        self.spec = spec
        self.inner = inner

    def __repr__(self) -> str:
        return f"CheckedDenoiser({self.spec!r})"

    def __call__(self, color: np.ndarray, albedo: np.ndarray, normal: np.ndarray) -> np.ndarray:
        """The plug-in's float32 ``(H, W, 3)`` denoised radiance, checked for shape, dtype and finiteness."""
        out = _call(self.spec, "denoising", self.inner, color, albedo, normal)
        if not isinstance(out, np.ndarray) or out.shape != color.shape or out.dtype.newbyteorder("=") != np.float32:
            raise PluginError(f"plug-in {self.spec!r}: the denoiser must return a float32 array of shape {color.shape}, "
                              f"got {_describe(out)}")
        if not np.isfinite(out).all():
            raise PluginError(f"plug-in {self.spec!r}: the denoiser returned {int(np.sum(~np.isfinite(out)))} NaN or infinite values")
        return np.ascontiguousarray(out, dtype=np.float32)  # native byte order, C order


def load_accelerator(spec: str, scene: Scene) -> CheckedAccelerator:
    """Build the accelerator ``spec`` names on ``scene``.

    Parameters
    ----------
    spec : str
        ``package.module:factory`` or a short name of :data:`ACCELERATOR_GROUP`
        (``local``, ``naive``, ``embree``, or any installed plug-in's).
    scene : Scene
        The geometry passed to the factory.

    Returns
    -------
    CheckedAccelerator
        The plug-in, every answer validated.
    """
    factory = resolve_factory(spec, ACCELERATOR_GROUP)
    return CheckedAccelerator(spec, _call(spec, "the factory", factory, scene), len(scene.triangles))


def load_denoiser(spec: str) -> CheckedDenoiser:
    """The denoiser ``spec`` names (``package.module:factory`` or a short name of :data:`DENOISER_GROUP`), validated."""
    factory = resolve_factory(spec, DENOISER_GROUP)
    return CheckedDenoiser(spec, _call(spec, "the factory", factory))


# ------------------------------------------------------------------ our own, registered in pyproject.toml
def local_kdtree(scene: Scene):
    """Factory of the paper's local-branch KD-tree (entry point ``local``)."""
    from kdtrace.kdtree import build_kdtree

    return build_kdtree(scene, "local")


def naive_kdtree(scene: Scene):
    """Factory of the naive KD-tree, Algorithm 1 (entry point ``naive``)."""
    from kdtrace.kdtree import build_kdtree

    return build_kdtree(scene, "naive")


def oidn() -> Callable:
    """Factory of Intel Open Image Denoise, :func:`reconstruction.baselines.oidn` (entry point ``oidn``)."""
    from reconstruction.baselines import oidn as denoise

    return denoise
