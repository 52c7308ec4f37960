"""Training loop, checkpoints and history (reconstruction/train.py), on the quick dataset with stand-in models."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch
from torch import nn

from kdtrace.config import DEFAULT_CONFIG
from reconstruction import train

SCENE = "cbox-original"
# the quick dataset, with small batches so three epochs are a dozen Adam steps
PROFILE = dataclasses.replace(DEFAULT_CONFIG.reconstruction.profile("quick"), batch_size=8, learning_rate=3e-3,
                              epochs=3)


def _psnr(test, reference):
    """PSNR (dB) of images clipped to [0, 1]: the convention of reconstruction.metrics, kept local."""
    mse = float(np.mean((np.clip(test, 0, 1) - np.clip(reference, 0, 1)) ** 2))
    return math.inf if mse == 0 else -10.0 * math.log10(mse)


class TinyDenoiser(nn.Module):
    """Stand-in: two 3x3 convolutions predicting a correction of the noisy RGB."""

    def __init__(self, width: int = 8) -> None:
        super().__init__()
        self.first = nn.Conv2d(6, width, 3, padding=1)
        self.second = nn.Conv2d(width, 3, 3, padding=1)

    def forward(self, x):
        return x[:, :3] + self.second(torch.relu(self.first(x)))


class OtherTiny(TinyDenoiser):
    """Same parameter shapes, another architecture."""


class TinyY(nn.Module):
    """Stand-in superresolution net on luma."""

    def __init__(self) -> None:
        super().__init__()
        self.first = nn.Conv2d(1, 4, 3, padding=1)
        self.second = nn.Conv2d(4, 1, 3, padding=1)

    def forward(self, y):
        return y + self.second(torch.relu(self.first(y)))


class InterruptAfter(nn.MSELoss):
    """MSE that raises KeyboardInterrupt at its ``limit``-th training call (gradients on)."""

    def __init__(self, limit: int) -> None:
        super().__init__()
        self.limit, self.calls = limit, 0

    def forward(self, prediction, target):
        if torch.is_grad_enabled():
            self.calls += 1
            if self.calls > self.limit:
                raise KeyboardInterrupt
        return super().forward(prediction, target)


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    with pytest.MonkeyPatch.context() as patch:
        directory = tmp_path_factory.mktemp("cache")
        patch.setenv("KDTRACE_CACHE", str(directory))
        yield directory


def _train(directory, loss_fn=None, model=None):
    torch.manual_seed(PROFILE.seed)
    return train.train_denoiser([SCENE], PROFILE, model=model or TinyDenoiser(), loss_fn=loss_fn or nn.MSELoss(),
                                directory=directory, psnr=_psnr, progress=False)


@pytest.fixture(scope="module")
def trained(cache):
    return _train(cache / "run")


def test_training_reduces_the_loss_and_writes_history_plot_and_checkpoints(trained):
    history = trained.history
    assert [row["epoch"] for row in history] == [1, 2, 3]
    losses = [row["train_loss"] for row in history]
    assert losses[-1] < losses[0]
    assert all(math.isfinite(row["validation_psnr"]) and math.isfinite(row["train_psnr"]) for row in history)
    best = min(history, key=lambda row: row["validation_loss"])
    assert trained.best_epoch == best["epoch"]
    assert json.loads((trained.directory / "history.json").read_text()) == history
    rows = (trained.directory / "history.csv").read_text().splitlines()
    assert rows[0].split(",")[:5] == ["epoch", "train_loss", "validation_loss", "train_psnr", "validation_psnr"]
    assert len(rows) == 4
    assert (trained.directory / "training.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    checkpoint = train.read_checkpoint(trained.directory / "checkpoint.pt")
    assert checkpoint["architecture"] == "TinyDenoiser" and checkpoint["epoch"] == 3
    assert checkpoint["parameters"] == train.parameter_count(TinyDenoiser()) == 6 * 8 * 9 + 8 + 8 * 3 * 9 + 3
    assert checkpoint["data_hash"] == trained.data_hash
    kept = train.read_checkpoint(trained.directory / "best.pt")
    assert kept["epoch"] == trained.best_epoch
    for name, value in trained.model.state_dict().items():
        torch.testing.assert_close(kept["model"][name], value)
    result = json.loads((trained.directory / "result.json").read_text())
    assert result["scenes"] == [SCENE] and set(result["test"]) >= {"psnr", "rmse", "loss"}
    assert result["warmup_steps"] == 0
    assert not [path for path in trained.directory.iterdir() if path.name.startswith(".")]


def test_interrupted_training_resumes_from_the_last_epoch(cache, trained):
    steps = math.ceil(len(train.denoiser_data([SCENE], PROFILE)[0]["train"][0]) / PROFILE.batch_size)
    with pytest.raises(KeyboardInterrupt):
        _train(cache / "interrupted", InterruptAfter(2 * steps + 1))
    assert train.read_checkpoint(cache / "interrupted" / "checkpoint.pt")["epoch"] == 2
    resumed_loss = InterruptAfter(10**9)
    resumed = _train(cache / "interrupted", resumed_loss)
    assert resumed_loss.calls == steps  # only the third epoch was trained
    for row, reference in zip(resumed.history, trained.history, strict=True):
        for name in ("train_loss", "validation_loss", "train_psnr", "validation_psnr"):
            assert row[name] == pytest.approx(reference[name], rel=1e-5)
    # a finished training is not trained again
    finished_loss = InterruptAfter(0)
    assert _train(cache / "interrupted", finished_loss).history == resumed.history and finished_loss.calls == 0


def test_wrong_architecture_or_foreign_checkpoint_is_a_clear_error(cache, trained):
    with pytest.raises(ValueError, match="holds a TinyDenoiser"):
        train.load_checkpoint(trained.directory / "best.pt", OtherTiny())
    with pytest.raises(ValueError, match="parameters"):
        train.load_checkpoint(trained.directory / "best.pt", TinyDenoiser(width=4))
    with pytest.raises(ValueError, match="holds a TinyDenoiser"):
        _train(trained.directory, model=OtherTiny())
    foreign = cache / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(ValueError, match="not a kdtrace reconstruction checkpoint"):
        train.load_checkpoint(foreign, TinyDenoiser())
    corrupt = cache / "corrupt.pt"
    corrupt.write_bytes((trained.directory / "best.pt").read_bytes()[:100])
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        train.load_checkpoint(corrupt, TinyDenoiser())
    model = TinyDenoiser()
    train.load_checkpoint(trained.directory / "best.pt", model)
    for name, value in trained.model.state_dict().items():
        torch.testing.assert_close(model.state_dict()[name], value)


def test_evaluate_reports_psnr_and_rmse_on_linear_values():
    target = torch.full((2, 3, 4, 4), 0.5)
    noisy = target + 0.1
    metrics = train.evaluate(nn.Identity(), (noisy, target), nn.MSELoss(), psnr=_psnr)
    assert metrics["rmse"] == pytest.approx(0.1, rel=1e-5)
    assert metrics["psnr"] == pytest.approx(20.0, rel=1e-5)
    assert metrics["loss"] == pytest.approx(0.01, rel=1e-4) and metrics["count"] == 2
    with pytest.raises(ValueError, match="non-empty"):
        train.evaluate(nn.Identity(), (noisy[:0], target[:0]), psnr=_psnr)


def test_superres_training_on_photos_and_renders(cache):
    profile = dataclasses.replace(PROFILE, epochs=2)
    torch.manual_seed(profile.seed)
    result = train.train_superres(profile, [SCENE], model=TinyY(), loss_fn=nn.MSELoss(), directory=cache / "sr",
                                  psnr=_psnr, progress=False)
    assert len(result.history) == 2
    record = json.loads((cache / "sr" / "result.json").read_text())
    assert record["architecture"] == "TinyY"
    assert math.isfinite(record["test"]["psnr"]) and math.isfinite(record["test"]["bicubic"]["psnr"])


def _synthetic_data(seed: int = 0):
    """Noisy 6-channel crops whose target is their first three channels without the noise."""
    generator = torch.Generator().manual_seed(seed)
    clean = torch.rand(48, 3, 16, 16, generator=generator)
    noisy = clean + 0.1 * torch.randn(48, 3, 16, 16, generator=generator)
    inputs = torch.cat([noisy, clean], dim=1)
    return {"train": (inputs[:32], clean[:32]), "validation": (inputs[32:], clean[32:])}


@pytest.mark.skipif(train.resolve_precision("auto")[0] != "bf16", reason="the CPU has no bf16 matrix hardware")
def test_bf16_mixed_precision_training_learns_and_keeps_fp32_weights(tmp_path):
    torch.manual_seed(1)
    result = train.fit(TinyDenoiser(), nn.MSELoss(), _synthetic_data(), tmp_path, "synthetic", epochs=4,
                       batch_size=8, learning_rate=3e-3, seed=1, psnr=_psnr, progress=False, precision="bf16")
    assert all(p.dtype == torch.float32 and p.is_contiguous() for p in result.model.parameters())
    losses = [row["validation_loss"] for row in result.history]
    assert min(losses[1:]) < losses[0]
    # the kept weights evaluate in fp32 to the recorded best validation loss (bf16 only in training)
    best = train.evaluate(result.model, _synthetic_data()["validation"], nn.MSELoss(), psnr=_psnr)["loss"]
    assert best == pytest.approx(min(losses), rel=1e-5)


def test_early_stopping_ends_after_patience_epochs_without_improvement(tmp_path):
    """A learning rate of 0 never improves on epoch 1: patience 2 stops after epoch 3, also on resume."""
    data = _synthetic_data()
    torch.manual_seed(2)
    result = train.fit(TinyDenoiser(), nn.MSELoss(), data, tmp_path, "synthetic", epochs=10, batch_size=8,
                       learning_rate=0.0, seed=2, psnr=_psnr, progress=False, patience=2)
    assert [row["epoch"] for row in result.history] == [1, 2, 3] and result.best_epoch == 1
    again = train.fit(TinyDenoiser(), nn.MSELoss(), data, tmp_path, "synthetic", epochs=10, batch_size=8,
                      learning_rate=0.0, seed=2, psnr=_psnr, progress=False, patience=2)
    assert len(again.history) == 3


def test_precision_names_are_checked():
    with pytest.raises(ValueError, match="precision"):
        train.resolve_precision("fp16")
    with pytest.raises(ValueError, match="precision"):
        dataclasses.replace(PROFILE, precision="half")


@pytest.mark.parametrize("decay", ["constant", "cosine"])
def test_warmup_and_decay_set_the_learning_rate_of_every_step_and_resume_on_schedule(cache, decay):
    """fit's schedule at every Adam step k of T: lr * min(1, (k + 1) / W), times (1 + cos(pi k / T)) / 2
    with the cosine decay; continued across a resume."""
    from torch.optim.optimizer import register_optimizer_step_pre_hook

    data, data_hash = train.denoiser_data([SCENE], PROFILE)
    steps = math.ceil(len(data["train"][0]) / PROFILE.batch_size)
    warmup = steps + 2  # the warm-up ends inside the second epoch
    total = 3 * steps
    expected = [PROFILE.learning_rate * min(1.0, (k + 1) / warmup)
                * (0.5 * (1.0 + math.cos(math.pi * k / total)) if decay == "cosine" else 1.0) for k in range(total)]

    class Interrupted(Exception):
        pass

    def run(directory, interrupt_at=None):
        rates = []

        def record(optimizer, *_):
            if len(rates) == interrupt_at:
                raise Interrupted  # before this Adam step: the last checkpoint is the epoch before
            rates.append(optimizer.param_groups[0]["lr"])

        hook = register_optimizer_step_pre_hook(record)
        try:
            torch.manual_seed(PROFILE.seed)
            train.fit(TinyDenoiser(), nn.MSELoss(), data, directory, data_hash, 3, PROFILE.batch_size,
                      PROFILE.learning_rate, PROFILE.seed, psnr=_psnr, progress=False, warmup_steps=warmup,
                      decay=decay)
        except Interrupted:
            pass
        finally:
            hook.remove()
        return rates

    assert run(cache / f"{decay}-whole") == pytest.approx(expected, rel=1e-12)
    # interrupted in the third epoch, then resumed: the third epoch is redone on the same schedule
    assert run(cache / f"{decay}-resumed", interrupt_at=2 * steps + 1) == pytest.approx(expected[:2 * steps + 1],
                                                                                       rel=1e-12)
    assert run(cache / f"{decay}-resumed") == pytest.approx(expected[2 * steps:], rel=1e-12)
    with pytest.raises(ValueError, match="warmup_steps"):
        train.fit(TinyDenoiser(), nn.MSELoss(), data, cache / "bad", data_hash, 1,
                  PROFILE.batch_size, PROFILE.learning_rate, PROFILE.seed, warmup_steps=-1)
    with pytest.raises(ValueError, match="decay"):
        train.fit(TinyDenoiser(), nn.MSELoss(), data, cache / "bad", data_hash, 1,
                  PROFILE.batch_size, PROFILE.learning_rate, PROFILE.seed, decay="linear")


def test_warmup_and_decay_are_part_of_the_model_key_only_when_used():
    model, loss = TinyDenoiser(), nn.MSELoss()
    rate = PROFILE.learning_rate
    plain = train._training_dir("denoiser", model, loss, "hash", PROFILE, rate)
    # old caches stay valid
    assert train._training_dir("denoiser", model, loss, "hash", PROFILE, rate, 0, "constant") == plain
    assert train._training_dir("denoiser", model, loss, "hash", PROFILE, rate, 100) != plain
    assert train._training_dir("denoiser", model, loss, "hash", PROFILE, 2e-3) != plain
    cosine = train._training_dir("denoiser", model, loss, "hash", PROFILE, rate, decay="cosine")
    assert cosine != plain
    # with a decay the epoch count shapes the schedule: more epochs is another model, not a resume
    longer = dataclasses.replace(PROFILE, epochs=PROFILE.epochs + 1)
    assert train._training_dir("denoiser", model, loss, "hash", longer, rate, decay="cosine") != cosine
    assert train._training_dir("denoiser", model, loss, "hash", longer, rate) == plain


def test_the_training_arithmetic_is_not_part_of_the_model_key():
    """A network trained in bf16 is found on a machine that would train in fp32, and the reverse."""
    model, loss = TinyDenoiser(), nn.MSELoss()
    keys = {train._training_dir("denoiser", model, loss, "hash", dataclasses.replace(PROFILE, precision=precision),
                                PROFILE.learning_rate) for precision in ("fp32", "bf16", "auto")}
    assert len(keys) == 1


def test_every_committed_network_sits_under_the_key_of_its_recorded_settings():
    """Each committed folder's name is the key this code computes from its ``result.json``, so any
    machine kind finds it (whatever precision it was trained in)."""
    from reconstruction.loss import SUPERRESOLUTION_SIGMA, EdgeAwareLoss
    from reconstruction.models import Denoiser, Superresolution

    folders = [folder for store in (train.REPOSITORY / "models").iterdir() for folder in store.iterdir()]
    assert folders
    for folder in folders:
        record = json.loads((folder / "result.json").read_text())
        assert sorted(path.name for path in folder.iterdir()) == sorted(train.PUBLISHED_FILES)
        settings = record["provenance"]["config"]
        kind = folder.name.split("-")[0]
        if kind == "denoiser":
            model = Denoiser(**record["kwargs"])
            loss = train.default_denoiser_loss(model, settings["denoiser_edge_range_floor"])
        else:
            model, loss = Superresolution(**record["kwargs"]), EdgeAwareLoss(SUPERRESOLUTION_SIGMA)
        assert train.parameter_count(model) == record["parameters"]
        profile = dataclasses.replace(PROFILE, batch_size=settings["batch_size"], seed=settings["seed"],
                                      epochs=settings["epochs"])
        directory = train._training_dir(kind, model, loss, record["data_hash"], profile, record["learning_rate"],
                                        record["warmup_steps"], record["decay"])
        assert directory.name == folder.name, f"{folder} is not found under its own key"


def test_epoch_counts_of_per_scene_denoisers_mixed_model_and_superresolution():
    base = dataclasses.replace(PROFILE, epochs=5)
    assert (base.denoiser.epochs, base.mixed.epochs) == (5, 5)  # 0: every model trains `epochs`
    longer = dataclasses.replace(base, denoiser_epochs=15)
    assert (longer.denoiser.epochs, longer.mixed.epochs, longer.epochs) == (15, 15, 5)
    own = dataclasses.replace(longer, mixed_epochs=6)
    # train_denoiser resolves `.denoiser` of whatever profile it is given, the mixed one included
    assert (own.mixed.epochs, own.mixed.denoiser.epochs, own.denoiser.epochs) == (6, 6, 15)
    with pytest.raises(ValueError, match="denoiser_epochs"):
        dataclasses.replace(base, denoiser_epochs=-1)


def test_a_scene_with_its_own_crop_count_changes_only_the_data_that_holds_it():
    plain, plain_hash = train.denoiser_data([SCENE], PROFILE)
    doubled = 2 * PROFILE.crops_per_view
    other = dataclasses.replace(PROFILE, crops_per_view_by_scene={"car": doubled})
    assert other.crops_per_view_by_scene == (("car", doubled),) and other.crops_for("car") == doubled
    # a scene without its own count keeps its crops and its key, so its cached models stay valid
    assert train.denoiser_data([SCENE], other)[1] == plain_hash
    own = dataclasses.replace(PROFILE, crops_per_view_by_scene={SCENE: doubled})
    more, more_hash = train.denoiser_data([SCENE], own)
    assert more_hash != plain_hash
    for split, (inputs, _) in plain.items():
        assert len(more[split][0]) == 2 * len(inputs)
    for bad in ({"car": "many"}, {"car": 0}):
        with pytest.raises(ValueError, match="crops_per_view_by_scene|counts"):
            dataclasses.replace(PROFILE, crops_per_view_by_scene=bad)


def test_a_denoiser_trains_for_the_profiles_denoiser_epochs(tmp_path):
    profile = dataclasses.replace(PROFILE, epochs=1, denoiser_epochs=2)
    torch.manual_seed(PROFILE.seed)
    result = train.train_denoiser([SCENE], profile, model=TinyDenoiser(), loss_fn=nn.MSELoss(),
                                  directory=tmp_path / "run", psnr=_psnr, progress=False)
    assert [row["epoch"] for row in result.history] == [1, 2]
    assert json.loads((tmp_path / "run" / "result.json").read_text())["provenance"]["config"]["epochs"] == 2


def test_the_perceptual_denoiser_is_calibrated_on_its_training_targets_and_trained_in_its_transfer(cache):
    from reconstruction.loss import EdgeAwareLoss, InSpace
    from reconstruction.metrics import auto_exposure
    from reconstruction.models import Denoiser

    profile = dataclasses.replace(PROFILE, epochs=1, denoiser_epochs=1)
    result = train.train_denoiser([SCENE], profile, perceptual=64.0, psnr=_psnr, progress=False)
    targets = train.denoiser_data([SCENE], profile)[0]["train"][1]
    linear = torch.expm1(targets).permute(0, 2, 3, 1).reshape(-1, targets.shape[-1], 3).numpy()
    assert float(result.model.radiance_gain) == pytest.approx(64.0 * auto_exposure(linear), rel=1e-5)
    assert math.isfinite(result.history[0]["validation_loss"])
    # another model than the paper net's, and its loss is taken in the transfer
    paper = train._training_dir("denoiser", Denoiser(), EdgeAwareLoss(), "hash", profile, 1e-3)
    perceptual = Denoiser(perceptual=64.0)
    in_space = InSpace(EdgeAwareLoss(), lambda z: z, "perceptual transfer of the net")
    assert train._training_dir("denoiser", perceptual, in_space, "hash", profile, 1e-3) != paper
    assert result.directory.name.startswith("denoiser-")


def test_profiles_warm_up_only_the_standard_normal_depth_variant():
    profiles = DEFAULT_CONFIG.reconstruction
    assert profiles.profile("standard").normal_depth_warmup_steps == 100
    assert profiles.profile("quick").normal_depth_warmup_steps == 0
    with pytest.raises(ValueError, match="normal_depth_warmup_steps"):
        dataclasses.replace(profiles.profile("quick"), normal_depth_warmup_steps=-1)


def test_denoiser_schedule_settings_default_to_the_constant_shared_rate_and_are_checked():
    quick = DEFAULT_CONFIG.reconstruction.profile("quick")
    # the quick profile (the CI gate's) keeps its models: constant rate, the shared learning_rate
    assert (quick.denoiser_decay, quick.denoiser_warmup_steps, quick.denoiser_rate) == ("constant", 0, quick.learning_rate)
    assert dataclasses.replace(quick, denoiser_learning_rate=2e-3).denoiser_rate == 2e-3
    for bad, match in (({"denoiser_decay": "linear"}, "denoiser_decay"), ({"denoiser_warmup_steps": -1}, "warmup"),
                       ({"denoiser_learning_rate": 0.0}, "denoiser_learning_rate")):
        with pytest.raises(ValueError, match=match):
            dataclasses.replace(quick, **bad)


def test_a_stored_model_is_reused_where_the_cache_lacks_it_and_checked(cache, tmp_path):
    profile = dataclasses.replace(PROFILE, epochs=1, model_store=str(tmp_path / "store"))

    def run(cache, loss_fn, model=None):
        torch.manual_seed(profile.seed)
        return train.train_denoiser([SCENE], profile, model=model or TinyDenoiser(), loss_fn=loss_fn,
                                    directory=cache / "denoiser-key", psnr=_psnr, progress=False)

    first = run(tmp_path / "machine-a", nn.MSELoss())
    stored = tmp_path / "store" / "denoiser-key"
    assert sorted(path.name for path in stored.iterdir()) == sorted(train.PUBLISHED_FILES)
    assert json.loads((stored / "result.json").read_text()) == json.loads((first.directory / "result.json").read_text())
    untrained = InterruptAfter(0)  # any training step raises
    again = run(tmp_path / "machine-b", untrained)
    assert untrained.calls == 0 and not (tmp_path / "machine-b").exists()
    assert again.directory == stored and again.history == first.history and again.best_epoch == first.best_epoch
    for name, value in first.model.state_dict().items():
        torch.testing.assert_close(again.model.state_dict()[name], value)
    assert not again.model.training
    # the stored copy wins over the cache's own training of the same key (the committed weights
    # are what every machine measures), and it is not written again
    stamps = {path.name: path.stat().st_mtime_ns for path in stored.iterdir()}
    assert run(tmp_path / "machine-a", InterruptAfter(0)).directory == stored
    assert {path.name: path.stat().st_mtime_ns for path in stored.iterdir()} == stamps
    with pytest.raises(ValueError, match="holds a TinyDenoiser"):
        run(tmp_path / "machine-c", nn.MSELoss(), OtherTiny())
    train.save_checkpoint(stored / "best.pt", TinyDenoiser(), "another-data-hash", epoch=1)
    with pytest.raises(ValueError, match="trained on data another-da"):
        run(tmp_path / "machine-c", nn.MSELoss())
    (stored / "best.pt").write_bytes(b"truncated")
    with pytest.raises(ValueError, match="not a readable checkpoint"):
        run(tmp_path / "machine-c", nn.MSELoss())


def test_the_networks_fingerprint_changes_with_the_stored_weights(tmp_path, monkeypatch):
    """Cached sweep and pipeline rows are keyed by it: retraining into the store by the same code
    must measure them again, and a store left as it was must reuse them."""
    from reconstruction.fingerprint import networks_fingerprint

    monkeypatch.setattr(train, "MODEL_STORE_ROOT", tmp_path)
    profile = dataclasses.replace(DEFAULT_CONFIG.reconstruction.profile("quick"), model_store="store")
    weights = tmp_path / "store" / "denoiser-0123" / "best.pt"
    weights.parent.mkdir(parents=True)
    weights.write_bytes(b"first weights")
    first = networks_fingerprint(profile)
    assert networks_fingerprint(profile) == first
    weights.write_bytes(b"retrained weights")
    assert networks_fingerprint(profile) != first
    assert networks_fingerprint(dataclasses.replace(profile, model_store="")) == networks_fingerprint()
