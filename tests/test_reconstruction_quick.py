"""Evaluate both committed reconstruction networks of the ``quick`` profile (``models/quick``).

The Cornell box quick dataset is generated in a private cache (Mitsuba references); the
per-scene denoiser and the superresolution net are the committed ones, found by the key of
this code's settings (a change of settings, data or architecture without
``scripts/retrain-quick.sh`` fails here instead of training silently). Both are measured on
the dataset's held-out **test views** (never used for training or for choosing the kept
epoch, which uses the validation split):

* the denoiser must beat the noisy input by at least :data:`DENOISER_MARGIN_DB` of PSNR
  pooled over the test views (OIDN is reported beside it, not asserted);
* the superresolution net must beat bicubic (pooled PSNR, strictly) on the scene's test
  views; on the held-out photo test set (:data:`reconstruction.evaluate.TEST_PHOTOS`) the
  quick net is below bicubic, a strict expected failure.

Training itself is covered by the fast tests of ``tests/test_reconstruction_train.py``.
The measured numbers are printed (``pytest -s`` or ``-rP`` shows them).
"""

from __future__ import annotations

import dataclasses
import importlib.util
import time

import pandas as pd
import pytest

from kdtrace.config import DEFAULT_CONFIG
from reconstruction import evaluate, train
from reconstruction.data import generate_dataset
from reconstruction.train import train_denoiser, train_superres

SCENE = "cbox-original"
#: The real training loop (the module's fixture replaces it by one that fails).
TRAINING = train.fit
PROFILE = DEFAULT_CONFIG.reconstruction.profile("quick")
#: Required PSNR gain of the denoiser over its noisy input on the test views (dB).
DENOISER_MARGIN_DB = 1.0
HAVE_OIDN = importlib.util.find_spec("pyoidn") is not None


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """Dataset, trained models and the seconds each stage took, in a module-wide private cache."""
    pytest.importorskip("mitsuba")
    with pytest.MonkeyPatch.context() as patch:
        cache = tmp_path_factory.mktemp("cache")
        patch.setenv("KDTRACE_CACHE", str(cache))

        def no_training(*args, **kwargs):
            raise AssertionError("the quick networks in models/quick are not those of this code's settings: "
                                 "retrain them with scripts/retrain-quick.sh")

        patch.setattr(train, "fit", no_training)
        patch.setattr(train, "MODEL_STORE_ROOT", train.REPOSITORY)  # the committed networks
        seconds = {}
        started = time.perf_counter()
        dataset = generate_dataset(SCENE, PROFILE, progress=False)
        seconds["dataset"] = time.perf_counter() - started
        started = time.perf_counter()
        denoiser = train_denoiser([SCENE], PROFILE, progress=False)
        seconds["denoiser"] = time.perf_counter() - started
        started = time.perf_counter()
        superres = train_superres(PROFILE, list(DEFAULT_CONFIG.profile("quick").reconstruction_scenes), progress=False)
        seconds["superres"] = time.perf_counter() - started
        print("\n[quick] seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in seconds.items()))
        yield {"dataset": dataset, "denoiser": denoiser, "superres": superres, "cache": cache}


def _report(title: str, results: dict[str, dict[str, float]]) -> None:
    print(f"\n[quick] {title} ({SCENE}, test views, pooled):")
    for method, metrics in results.items():
        print(f"  {method:8s} PSNR {metrics['psnr']:7.3f} dB  RMSE {metrics['rmse']:.5f}  "
              f"(mean per-image PSNR {metrics['psnr_mean']:.3f}, {metrics['images']} images)")


def test_denoiser_beats_the_noisy_input_on_test_views(trained):
    results = evaluate.denoiser_quality(trained["denoiser"].model, trained["dataset"], "test", with_oidn=HAVE_OIDN)
    _report(f"denoising, kept epoch {trained['denoiser'].best_epoch}/{PROFILE.epochs}", results)
    gain = results["ours"]["psnr"] - results["noisy"]["psnr"]
    print(f"  gain over noisy {gain:+.3f} dB" + (f", ours - OIDN {results['ours']['psnr'] - results['oidn']['psnr']:+.3f} dB"
                                                 if HAVE_OIDN else ""))
    assert gain >= DENOISER_MARGIN_DB, results


def test_superresolution_beats_bicubic_on_test_views(trained):
    results = evaluate.superres_quality(trained["superres"].model, trained["dataset"], "test",
                                        PROFILE.superres_downsample)
    _report(f"superresolution 2x, kept epoch {trained['superres'].best_epoch}/{PROFILE.epochs}", results)
    gain = results["ours"]["psnr"] - results["bicubic"]["psnr"]
    print(f"  gain over bicubic {gain:+.3f} dB")
    assert gain > 0.0, results


@pytest.mark.xfail(strict=True, reason=(
    "the committed quick superresolution net (32x32 crops, 40 epochs) is 0.45 dB below bicubic on the held-out "
    "photos; the standard one is above it (Table 5). Strict: a quick net that beats bicubic here must say so."))
def test_superresolution_beats_bicubic_on_the_held_out_photos(trained):
    """The photo test set (never used in training or model choice; chosen before any evaluation)."""
    photos = [evaluate.held_out_photo(name) for name in evaluate.TEST_PHOTOS]
    results = evaluate.superres_images(trained["superres"].model, photos, PROFILE.superres_downsample)
    _report(f"superresolution 2x on the held-out photos {evaluate.TEST_PHOTOS}", results)
    gain = results["ours"]["psnr"] - results["bicubic"]["psnr"]
    print(f"  gain over bicubic {gain:+.3f} dB, over Lanczos {results['ours']['psnr'] - results['lanczos']['psnr']:+.3f} dB")
    assert gain > 0.0, results


def test_untrained_superresolution_is_exactly_bicubic():
    import torch

    from reconstruction.models import Superresolution

    y = torch.rand(2, 1, 16, 16)
    assert torch.equal(Superresolution()(y), y)


def test_main_quality_reuses_the_models_and_writes_the_table(trained, tmp_path, monkeypatch):
    # the committed denoiser; a superresolution net trained on this one scene (not a committed network),
    # for 2 epochs and never published into the checkout
    monkeypatch.setattr(train, "fit", TRAINING)
    monkeypatch.setattr(train, "_publish", lambda result, profile: None)
    monkeypatch.setattr(train, "MODEL_STORE_ROOT", train.REPOSITORY)
    started = time.perf_counter()
    table = evaluate.main_quality([SCENE], dataclasses.replace(PROFILE, epochs=2), tmp_path, with_oidn=HAVE_OIDN,
                                  progress=False)
    print(f"\n[quick] main_quality with cached models: {time.perf_counter() - started:.1f} s\n"
          + evaluate.to_markdown(table))
    assert list(table.columns) == list(evaluate.COLUMNS)
    methods = {(row.task, row.method) for row in table.itertuples()}
    assert {("denoise", "noisy"), ("denoise", "ours"), ("superres", "bicubic"), ("superres", "ours")} <= methods
    assert (("denoise", "oidn") in methods) == HAVE_OIDN
    # the same (cached) models as the fixture's: the same numbers
    ours = table.set_index(["task", "method"]).loc[("denoise", "ours"), "psnr"]
    direct = evaluate.denoiser_quality(trained["denoiser"].model, trained["dataset"], "test", with_oidn=False)
    assert ours == pytest.approx(direct["ours"]["psnr"], abs=1e-9)
    assert (tmp_path / "quality.md").read_text().startswith("| scene |")
    pd.testing.assert_frame_equal(pd.read_csv(tmp_path / "quality.csv"), table, check_dtype=False)


def test_pooled_psnr_is_not_the_mean_of_per_image_psnrs():
    import numpy as np

    flat, busy = np.full((4, 4, 3), 0.5), np.full((4, 4, 3), 0.25)
    metrics = evaluate.pooled([flat + 1e-4, busy + 0.1], [flat, busy])
    assert metrics["psnr"] == pytest.approx(-10 * np.log10((1e-8 + 0.01) / 2))
    assert metrics["psnr_mean"] == pytest.approx((80.0 + 20.0) / 2)
    # display-referred: each view tonemapped with its own reference's exposure, then pooled the same way
    from reconstruction import metrics as image_metrics

    rng = np.random.default_rng(0)
    references = [rng.uniform(0.01, 0.2, (8, 8, 3)), rng.uniform(0.5, 3.0, (8, 8, 3))]
    predictions = [reference * rng.uniform(0.8, 1.2, reference.shape) for reference in references]
    views = [image_metrics.display_metrics(p, r) for p, r in zip(predictions, references, strict=True)]
    both = evaluate.pooled(predictions, references)
    assert both["display_rmse"] == pytest.approx(np.sqrt(np.mean([v["display_rmse"] ** 2 for v in views])))
    assert both["flip"] == pytest.approx(np.mean([v["flip"] for v in views]))
    assert both["relmse"] == pytest.approx(np.mean([image_metrics.relmse(p, r) for p, r in zip(predictions, references, strict=True)]))
    # a view no light reaches has no exposure of its own: it is shown with the others' (and counted)
    black = evaluate.pooled([predictions[0], np.full((8, 8, 3), 0.01)], [references[0], np.zeros((8, 8, 3))])
    exposure = image_metrics.auto_exposure(references[0])
    expected = np.mean([image_metrics.display_metrics(predictions[0], references[0])["display_rmse"] ** 2,
                        image_metrics.display_metrics(np.full((8, 8, 3), 0.01), np.zeros((8, 8, 3)), exposure)["display_rmse"] ** 2])
    assert black["black_references"] == 1 and black["display_rmse"] == pytest.approx(np.sqrt(expected))
    with pytest.raises(ValueError, match="all 1 references are black"):
        evaluate.pooled([predictions[0]], [np.zeros((8, 8, 3))])
    # and combine() of the parts is pooled() of the whole
    parts = evaluate.combine([evaluate.pooled(predictions[:1], references[:1]), evaluate.pooled(predictions[1:], references[1:])])
    for name in ("psnr", "display_psnr", "flip", "relmse", "smape"):
        assert parts[name] == pytest.approx(both[name])
    with pytest.raises(ValueError):
        evaluate.pooled([], [])


#: The quick report's sweep spp (never below the input at any of them).
SWEEP_SPP = DEFAULT_CONFIG.profile("quick").sweep_spp


def test_denoiser_blended_with_its_input_is_not_below_the_input_at_any_sweep_spp(trained):
    """Weights fitted on the validation views; measured on the test views rendered at each sweep spp.

    The raw network (trained at 4 spp) loses to its own input at high spp; the blend of
    :mod:`reconstruction.blend` (capped by each frame's own bound from two halves of its
    samples) must not, in linear PSNR, display PSNR or FLIP. The quick networks are worse
    than their input by FLIP at every spp, so that blend may be the input itself; the blend
    with the weights fitted in the linear space alone must keep the network's linear gain at
    4 spp and never lose to the input in linear PSNR.
    """
    from kdtrace.render import render
    from kdtrace.scenes import load_scene
    from reconstruction.blend import BlendWeights, combine_halves, fit_blend_weights, frame_weight_cap, view_seed
    from reconstruction.data import view_camera
    from reconstruction.inference import denoise

    model, dataset, scene = trained["denoiser"].model, trained["dataset"], load_scene(SCENE)
    weights = fit_blend_weights(model, dataset, scene, SWEEP_SPP, PROFILE.max_depth, PROFILE.seed)
    records = {view["name"]: view for view in dataset.manifest["views"]}
    print(f"\n[quick] blend weights ({SCENE}, {weights.views} validation views): "
          + ", ".join(f"{s} spp {w:.2f} ({weights.limiting_space(s)})"
                      for s, w in zip(weights.spp, weights.weights, strict=True)))
    linear = BlendWeights(weights.spp, weights.by_space["linear"], weights.views)
    below = {}
    for spp in SWEEP_SPP:
        outputs = {"noisy": [], "raw": [], "blend": [], "linear blend": []}
        references = []
        for name in dataset.views("test"):
            record = records[name]
            camera = view_camera(record)
            def samples(count, first, record=record, camera=camera, spp=spp):
                # the test seed stream differs from the validation fit's (another split, another index)
                return render(scene, spp=count, max_depth=PROFILE.max_depth, first_sample=first,
                              seed=view_seed(PROFILE.seed + 1, record["index"], spp),
                              width=camera.width, height=camera.height, aux=True, camera=camera)

            if spp < 2:
                frame = samples(spp, 0)
                rgb, albedo, cap = frame.rgb, frame.albedo, 1.0
            else:
                halves = (samples(spp // 2, 0), samples(spp // 2, spp // 2))
                rgb, albedo = combine_halves(*halves)
                cap = frame_weight_cap(lambda c, a: denoise(model, c, a), *halves)
            reference = dataset.load_view(name)["reference"]
            raw = evaluate.denoise_view(model, {"noisy": rgb, "albedo": albedo, "reference": reference})
            outputs["noisy"].append(rgb)
            outputs["raw"].append(raw)
            outputs["blend"].append(weights.apply(rgb, raw, spp, cap))
            outputs["linear blend"].append(linear.apply(rgb, raw, spp, cap))
            references.append(reference)
        scores = {method: evaluate.pooled(images, references) for method, images in outputs.items()}
        print(f"  {spp:3d} spp: " + "  ".join(f"{m} {s['psnr']:6.2f} dB, {s['display_psnr']:6.2f} dB display, "
                                              f"FLIP {s['flip']:.4f}" for m, s in scores.items()))
        blend_, noisy = scores["blend"], scores["noisy"]
        if (blend_["psnr"] < noisy["psnr"] or blend_["display_psnr"] < noisy["display_psnr"]
                or blend_["flip"] > noisy["flip"] or scores["linear blend"]["psnr"] < noisy["psnr"]):
            below[spp] = {method: {key: score[key] for key in ("psnr", "display_psnr", "flip")}
                          for method, score in scores.items()}
        if spp == PROFILE.spp:
            assert scores["linear blend"]["psnr"] >= noisy["psnr"] + DENOISER_MARGIN_DB, scores
    assert not below, below


def test_blown_up_and_collapsed_outputs_are_counted_apart_from_the_psnr():
    import numpy as np

    noisy = np.full((4, 4, 3), 0.2)
    noisy[0, 0] = 0.8  # the frame's brightest value
    noisy[3, 3] = 0.0  # no light here
    output = np.full((4, 4, 3), 0.2)
    output[1, 1, 2] = 0.81  # one channel above anything in the input: blown up
    output[2, 2] = 0.0  # black where the input has light: collapsed
    output[3, 3] = 0.0  # black where the input is black: fine
    assert evaluate.beyond_input([output], [noisy]) == 1
    assert evaluate.black_where_lit([output], [noisy]) == 1
    assert evaluate.beyond_input([noisy], [noisy]) == evaluate.black_where_lit([noisy], [noisy]) == 0
