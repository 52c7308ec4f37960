"""Fuzz tests of the plug-in boundary: every wrong answer of an accelerator or denoiser is caught.

A fake accelerator and a fake denoiser return a valid answer spoiled by one to three
drawn defects: the wrong container or length, every wrong shape, dtype (float16,
longdouble, complex, object, str, bool, int for floats and float for indices),
byte order and memory order (big-endian, strided, reversed, Fortran-ordered, read-only),
NaN and infinities, and triangle indices out of range. The property: the checked
wrapper (:class:`kdtrace.plugins.CheckedAccelerator`, :class:`kdtrace.plugins.CheckedDenoiser`)
either raises :class:`kdtrace.plugins.PluginError` whose message starts with
``plug-in 'SPEC': `` or hands on an answer that keeps the documented contract
(:func:`assert_keeps_contract`, :func:`assert_image_keeps_contract`), C-contiguous
and in native byte order; never another exception. Example counts as in
``tests/test_fuzz_readers.py`` (``KDTRACE_FUZZ_EXAMPLES`` for a soak).
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from hypothesis import event, given
from hypothesis import strategies as st

from kdtrace.plugins import CheckedAccelerator, CheckedDenoiser, PluginError
from kdtrace.procedural import random_soup
from tests.strategies import fuzz

SPEC = "fuzz_plugins:make"
SCENE = random_soup(20, seed=5)
T = len(SCENE.triangles)
N = 16


def _valid_answer(rng: np.random.Generator) -> list[np.ndarray]:
    """A valid (t, tri, u, v) for :data:`N` rays: about half hits."""
    hit = rng.random(N) < 0.5
    t = np.where(hit, rng.uniform(0.1, 5.0, N), np.inf)
    tri = np.where(hit, rng.integers(0, T, N), -1).astype(np.int32)
    u = np.where(hit, rng.uniform(0, 0.5, N), 0.0)
    v = np.where(hit, rng.uniform(0, 0.5, N), 0.0)
    return [t, tri, u, v]


def _respell(value: np.ndarray, how: str) -> object:
    """``value`` with the same numbers in another dtype, byte order, memory layout or container."""
    if how == "big-endian":
        return value.astype(value.dtype.newbyteorder(">"))
    if how == "strided":
        return np.repeat(value, 2)[::2]
    if how == "reversed":
        return value[::-1].copy()[::-1]
    if how == "read-only":
        value = value.copy()
        value.flags.writeable = False
        return value
    if how == "fortran-2d":
        return np.asfortranarray(value.reshape(-1, 1))
    if how == "list":
        return value.tolist()
    if how == "column":
        return value.reshape(-1, 1)
    if how == "row":
        return value.reshape(1, -1)
    if how == "scalar":
        return value[0]
    if how == "short":
        return value[:-1]
    if how == "long":
        return np.concatenate([value, value[:1]])
    if how == "empty":
        return value[:0]
    return value.astype(how)  # a dtype name


LAYOUTS = ("big-endian", "strided", "reversed", "read-only", "fortran-2d", "list", "column", "row", "scalar", "short", "long",
           "empty")
DTYPES = ("float16", "float32", "float64", "longdouble", "complex128", "object", "str", "bool", "int8", "int32", "int64",
          "uint8", "uint64")
POISON = (np.nan, np.inf, -np.inf, 1e308, -1.0, 0.0)


@st.composite
def spoiled_answers(draw):
    """(answer, what was done): a valid intersect answer with one to three defects."""
    answer: object = _valid_answer(np.random.default_rng(draw(st.integers(0, 2**16))))
    done = []
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["layout", "dtype", "poison", "index", "container"]))
        if kind == "container" or not isinstance(answer, list):
            how = draw(st.sampled_from(["tuple", "list", "3-tuple", "5-tuple", "none", "array"]))
            done.append(how)
            answer = {"tuple": lambda a: tuple(a), "list": lambda a: list(a), "3-tuple": lambda a: tuple(a)[:3],
                      "5-tuple": lambda a: (*a, a[0]), "none": lambda a: None,
                      "array": lambda a: np.zeros((4, N))}[how](answer if isinstance(answer, list | tuple) else [0] * 4)
            break
        k = draw(st.integers(0, 3))
        with warnings.catch_warnings(), np.errstate(all="ignore"):
            warnings.simplefilter("ignore")  # casts that lose information are the point
            try:
                how = _spoil(draw, answer, kind, k)
            except (ValueError, TypeError, IndexError, OverflowError):  # a defect that does not apply to an earlier one
                continue
        done.append(f"{kind} {how} of {'t tri u v'.split()[k]}")
    return (tuple(answer) if isinstance(answer, list) else answer), done


def _spoil(draw, answer: list, kind: str, k: int) -> str:
    """Apply one defect of ``kind`` to ``answer[k]`` in place; what was done."""
    if kind == "layout":
        how = draw(st.sampled_from(LAYOUTS))
        answer[k] = _respell(np.asarray(answer[k]), how)
    elif kind == "dtype":
        how = draw(st.sampled_from(DTYPES))
        answer[k] = _respell(np.asarray(answer[k]), how)
    elif kind == "poison":
        how = str(draw(st.sampled_from(POISON)))
        spoiled = np.array(answer[k], dtype=np.float64 if k != 1 else np.asarray(answer[k]).dtype, copy=True)
        if spoiled.dtype.kind == "f" and spoiled.ndim == 1 and len(spoiled):
            spoiled[draw(st.integers(0, len(spoiled) - 1))] = float(how)
        answer[k] = spoiled
    else:
        how = str(draw(st.sampled_from([T, T + 1, -2, 2**31 - 1, -(2**31), 2**40])))
        tri = np.array(answer[1], copy=True)
        if tri.ndim == 1 and len(tri) and tri.dtype.kind in "iuf":
            tri[draw(st.integers(0, len(tri) - 1))] = np.array(int(how)).astype(tri.dtype) if tri.dtype.kind != "f" else float(how)
        answer[1] = tri
    return how


class _Fake:
    """An accelerator answering every query with a fixed (spoiled) answer."""

    def __init__(self, answer, occluded=None, stats=None) -> None:
        self.answer, self.occlusion, self.stats = answer, occluded, stats

    def intersect(self, origins, directions, tmin=0.0, tmax=np.inf):
        return self.answer

    def occluded(self, origins, directions, tmax):
        return self.occlusion


def _rays() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    return rng.uniform(-1, 1, (N, 3)), rng.normal(size=(N, 3))


def assert_keeps_contract(answer) -> None:
    """What ``intersect`` promises its callers (``kdtrace.plugins.Accelerator``)."""
    t, tri, u, v = answer
    for value in answer:
        assert isinstance(value, np.ndarray) and value.shape == (N,), value
        assert value.flags.c_contiguous and value.dtype.isnative, value.dtype
    assert t.dtype in (np.float32, np.float64) and u.dtype == t.dtype and v.dtype == t.dtype or all(
        a.dtype in (np.float32, np.float64) for a in (t, u, v)), (t.dtype, u.dtype, v.dtype)
    assert tri.dtype.kind in "iu" and np.all((tri >= -1) & (tri < T))
    hit = tri >= 0
    assert np.array_equal(np.isfinite(t), hit) and np.all(t[~hit] == np.inf)
    assert np.all(np.isfinite(u[hit])) and np.all(np.isfinite(v[hit]))


def _plugin_error_or(fn, check) -> None:
    try:
        result = fn()
    except PluginError as error:
        event("refused")
        assert str(error).startswith(f"plug-in {SPEC!r}: "), error
    else:
        event("accepted")
        check(result)


@fuzz()
@given(spoiled=spoiled_answers())
def test_every_spoiled_intersect_answer_is_caught_or_keeps_the_contract(spoiled):
    answer, _ = spoiled
    accelerator = CheckedAccelerator(SPEC, _Fake(answer), T)
    _plugin_error_or(lambda: accelerator.intersect(*_rays()), assert_keeps_contract)


@fuzz()
@given(occlusion=st.tuples(st.sampled_from(["bool", "int8", "float64", "object", "uint8"]),
                           st.sampled_from(["as is", *LAYOUTS])))
def test_every_spoiled_occlusion_answer_is_caught_or_keeps_the_contract(occlusion):
    dtype, layout = occlusion
    value = np.random.default_rng(1).random(N) < 0.5
    answer = _respell(value.astype(dtype), layout) if layout != "as is" else value.astype(dtype)
    accelerator = CheckedAccelerator(SPEC, _Fake(None, occluded=answer), T)

    def check(result):
        assert isinstance(result, np.ndarray) and result.shape == (N,) and result.dtype == np.bool_
        assert result.flags.c_contiguous

    _plugin_error_or(lambda: accelerator.occluded(*_rays(), np.inf), check)


@fuzz(60)
@given(stats=st.one_of(st.none(), st.just({}), st.text(max_size=3), st.integers(), st.lists(st.integers(), max_size=3),
                       st.just([("references", 3)]), st.dictionaries(st.sampled_from(["references", "bytes", "nodes", "x"]),
                                                                     st.one_of(st.integers(), st.floats(), st.text(max_size=2)))))
def test_any_stats_are_taken_as_a_dict_or_refused_naming_the_plugin(stats):
    _plugin_error_or(lambda: CheckedAccelerator(SPEC, _Fake(None, stats=stats), T), lambda a: isinstance(a.stats, dict))


def assert_image_keeps_contract(out: np.ndarray, shape: tuple[int, ...]) -> None:
    """What a checked denoiser hands on: float32, the input's shape, finite, C-contiguous."""
    assert isinstance(out, np.ndarray) and out.shape == shape and out.dtype == np.float32
    assert out.flags.c_contiguous and np.isfinite(out).all()


@fuzz()
@given(how=st.lists(st.one_of(st.sampled_from(("big-endian", "strided-image", "fortran", "reversed-image", "read-only-image",
                                                "list", "transposed", "channel-first", "2d", "batch", "scalar", "matrix")),
                              st.sampled_from(DTYPES), st.sampled_from(POISON)), min_size=1, max_size=3))
def test_every_spoiled_denoiser_output_is_caught_or_keeps_the_contract(how):
    rng = np.random.default_rng(2)
    color = rng.random((6, 5, 3), dtype=np.float32)

    def denoise(color, albedo, normal):
        out: object = color.copy()
        for step in how:
            if not isinstance(out, np.ndarray):
                break
            if isinstance(step, float):
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # complex to real: the point
                    out = out.astype(np.float64)
                out.flat[3] = step
            elif step in DTYPES:
                with np.errstate(invalid="ignore", over="ignore"), warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # complex to real: the point
                    out = out.astype(step)
            else:
                out = {"big-endian": lambda o: o.astype(o.dtype.newbyteorder(">")),
                       "strided-image": lambda o: np.repeat(o, 2, axis=1)[:, ::2],
                       "fortran": np.asfortranarray, "reversed-image": lambda o: o[::-1].copy()[::-1],
                       "read-only-image": lambda o: np.lib.stride_tricks.as_strided(o, writeable=False),
                       "list": lambda o: o.tolist(), "transposed": lambda o: o.transpose(1, 0, 2),
                       "channel-first": lambda o: o.transpose(2, 0, 1), "2d": lambda o: o[..., 0],
                       "batch": lambda o: o[None], "scalar": lambda o: o.flat[0],
                       "matrix": lambda o: o.reshape(-1, 3)}[step](out)
        return out

    checked = CheckedDenoiser(SPEC, denoise)
    _plugin_error_or(lambda: checked(color, color, color), lambda out: assert_image_keeps_contract(out, color.shape))


@pytest.mark.parametrize(("answer", "message"), [
    ((np.full(N, -np.inf), np.full(N, -1), np.zeros(N), np.zeros(N)), "t[0] = -inf with tri[0] = -1"),
    ((np.ones(N), np.zeros(N, np.int32), np.full(N, np.inf), np.zeros(N)), "u[0] = inf"),
    ((np.ones(N, np.float16), np.zeros(N, np.int32), np.zeros(N), np.zeros(N)), "t must be a float32 or float64 array"),
])
def test_regressions_infinite_answers_and_half_floats_are_caught(answer, message):
    with pytest.raises(PluginError, match=f"plug-in {SPEC!r}: ") as error:
        CheckedAccelerator(SPEC, _Fake(answer), T).intersect(*_rays())
    assert message in str(error.value)


def test_regression_stats_that_are_not_a_mapping_name_the_plugin():
    with pytest.raises(PluginError, match=f"plug-in {SPEC!r}: stats must be a dict, got str"):
        CheckedAccelerator(SPEC, _Fake(None, stats="fast"), T)
