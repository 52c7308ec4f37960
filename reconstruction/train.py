"""Training of the reconstruction networks on CPU (paper §4.3, §5.2, §6.1).

Adam with mini-batches (``batch_size``, 32 in the paper) for ``epochs`` epochs; after
every epoch the train and validation loss and PSNR are recorded, and the weights with
the lowest validation loss are kept (the paper's model choice). Everything needed to
continue lives in ``checkpoint.pt`` (model, optimizer, epoch, RNG states, history, best
weights), written atomically after each epoch: an interrupted training reruns from the
epoch after the last finished one and gives the same result as an uninterrupted one.
``best.pt`` holds the kept weights. ``history.json``, ``history.csv`` and
``training.png`` (the paper's Figure 4: loss and PSNR per epoch) are rewritten each epoch
(the plot only every :data:`PLOT_EVERY` epochs and after the last, since drawing it costs
about a third of a quick-profile epoch).

Checkpoints record the architecture name and constructor arguments, the parameter count
and the hash of the training data; :func:`load_checkpoint` refuses a checkpoint of
another architecture, a foreign or corrupt file, with a ``ValueError``.

Entry points: :func:`train_denoiser` (one scene: the Precision Graphics model; several:
the mixed model), :func:`train_superres`, :func:`evaluate`. The training folder is
``cache_root()/models/<kind>-<key>`` where the key hashes the architecture, the loss, the data
hash and the optimisation settings (not the epoch count, so raising ``epochs`` resumes).

A profile with a ``model_store`` (``quick`` and ``standard``) also copies each finished model's
kept weights, history, plot and ``result.json`` to ``<model_store>/<kind>-<key>``, a folder
meant to be committed: every machine then evaluates that model instead of training it again
(:func:`_published_result`). The stored copy wins over the cache, so a PSNR measured with a
committed network is a measurement of the same weights on every machine kind. The training
arithmetic (fp32 or bf16, :func:`resolve_precision`) is recorded in ``result.json`` as
provenance and is not part of the key: a network trained in bf16 on one machine is found and
used on a machine that would train in fp32. Only finished models are copied, so a training
interrupted on a machine that is then lost restarts from its first epoch.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import io
import json
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from kdtrace.cache import atomic_write, atomic_write_bytes, cache_root, claim, content_key
from kdtrace.config import DECAYS, ReconstructionProfile
from kdtrace.provenance import stamp
from reconstruction.data import resolve_profile

#: The checkout holding ``kdtrace``, ``reconstruction`` and the committed ``models``.
REPOSITORY = Path(__file__).resolve().parents[1]
#: Where a profile's relative ``model_store`` is found (the checkout).
MODEL_STORE_ROOT = REPOSITORY
#: Identifies our checkpoint files; bump the version when their layout changes.
CHECKPOINT_FORMAT = "kdtrace-reconstruction-checkpoint"
CHECKPOINT_VERSION = 1
#: training.png is redrawn every this many epochs and after the last one.
PLOT_EVERY = 10
#: Examples per forward pass when evaluating (memory bound only; results do not depend on it).
EVAL_BATCH = 64
#: A finished model's files copied to its profile's ``model_store``; ``result.json`` last, since
#: its presence says the copy is complete.
PUBLISHED_FILES = ("best.pt", "history.json", "history.csv", "training.png", "result.json")

Transform = Callable[[torch.Tensor], torch.Tensor]


@dataclass
class TrainResult:
    """Outcome of a training run.

    Attributes
    ----------
    model : nn.Module
        The model, holding the kept (lowest validation loss) weights, in eval mode.
    history : list of dict
        Per epoch: ``epoch`` (1-based), ``train_loss``, ``validation_loss``,
        ``train_psnr``, ``validation_psnr`` (dB) and ``seconds``.
    best_epoch : int
        Epoch of the kept weights.
    directory : Path
        Folder of the checkpoints, history and plot.
    data_hash : str
        Hash of the training data recorded in the checkpoints.
    """

    model: nn.Module
    history: list[dict[str, float]]
    best_epoch: int
    directory: Path
    data_hash: str


def architecture(model: nn.Module) -> dict[str, Any]:
    """Name and constructor arguments of ``model`` (its ``config`` property when it has one)."""
    config = getattr(model, "config", None)
    return dict(config) if isinstance(config, dict) else {"architecture": type(model).__name__, "kwargs": {}}


def parameter_count(model: nn.Module) -> int:
    """Trainable parameters of ``model``."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


# ------------------------------------------------------------------ checkpoints
def save_checkpoint(path: Path, model: nn.Module, data_hash: str, **state: Any) -> None:
    """Atomically write ``model``'s weights with its identity and ``state`` to ``path``."""
    payload = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, **architecture(model),
               "parameters": parameter_count(model), "data_hash": data_hash, "model": model.state_dict(), **state}
    buffer = io.BytesIO()
    torch.save(payload, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The contents of a checkpoint written by :func:`save_checkpoint` (tensors on CPU).

    Raises
    ------
    ValueError
        Missing, unreadable, foreign or of another layout version.
    """
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # torch.load raises many types (OSError, pickle and zip errors) on bad files
        raise ValueError(f"{path} is not a readable checkpoint: {error}") from error
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a kdtrace reconstruction checkpoint")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise ValueError(f"{path} has checkpoint version {payload.get('version')}, expected {CHECKPOINT_VERSION}")
    return payload


def load_checkpoint(path: str | Path, model: nn.Module, weights: str = "model") -> dict[str, Any]:
    """Load a checkpoint's weights into ``model`` after checking it was made for it.

    Parameters
    ----------
    path : str or Path
    model : nn.Module
        Receives the weights (in place).
    weights : {"model", "best"}
        Which weights of ``checkpoint.pt`` to load (``best.pt`` has only ``"model"``).

    Returns
    -------
    dict
        The whole checkpoint (see :func:`save_checkpoint`).

    Raises
    ------
    ValueError
        Not a checkpoint, another architecture or constructor arguments, another
        parameter count, or weights that do not fit.
    """
    payload = read_checkpoint(path)
    expected = architecture(model)
    found = {key: payload.get(key) for key in ("architecture", "kwargs", *expected)}
    if found != expected:
        raise ValueError(f"{path} holds a {found['architecture']} {found['kwargs']} checkpoint "
                         f"({ {k: v for k, v in found.items() if k not in ('architecture', 'kwargs')} }); "
                         f"the model is a {expected['architecture']} {expected['kwargs']}")
    if payload.get("parameters") != parameter_count(model):
        raise ValueError(f"{path} has {payload.get('parameters')} parameters; the model has {parameter_count(model)}")
    try:
        model.load_state_dict(payload[weights])
    except (KeyError, RuntimeError) as error:
        raise ValueError(f"{path}: weights {weights!r} do not fit the model: {error}") from error
    return payload


# ------------------------------------------------------------------ history
def _write_history(directory: Path, history: list[dict[str, float]], plot: bool = True) -> None:
    """history.json, history.csv and (if ``plot``) training.png (Figure 4), each atomically."""
    atomic_write_bytes(directory / "history.json", json.dumps(history, indent=1).encode())
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=list(history[0]))
    writer.writeheader()
    writer.writerows(history)
    atomic_write_bytes(directory / "history.csv", text.getvalue().encode())
    if plot:
        plot_history(history, directory / "training.png")


def plot_history(history: list[dict[str, float]], path: Path) -> Path:
    """Plot loss and PSNR of the train and validation sets per epoch (the paper's Figure 4) to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [row["epoch"] for row in history]
    figure, (loss_axes, psnr_axes) = plt.subplots(1, 2, figsize=(9, 3.5))
    for axes, quantity, label in ((loss_axes, "loss", "loss"), (psnr_axes, "psnr", "PSNR (dB)")):
        for split, style in (("train", "-o"), ("validation", "--s")):
            axes.plot(epochs, [row[f"{split}_{quantity}"] for row in history], style, markersize=3, label=split)
        axes.set_xlabel("epoch")
        axes.set_ylabel(label)
        axes.grid(alpha=0.3)
        axes.legend()
    figure.tight_layout()
    atomic_write(path, lambda temporary: figure.savefig(temporary, dpi=100))
    plt.close(figure)
    return path


# ------------------------------------------------------------------ training loop
def _default_psnr() -> Callable[[np.ndarray, np.ndarray], float]:
    from reconstruction.metrics import psnr

    return psnr


def _identity(x: torch.Tensor) -> torch.Tensor:
    return x


def _batches(count: int, size: int, order: np.ndarray | None = None):
    order = np.arange(count) if order is None else order
    for start in range(0, count, size):
        yield torch.from_numpy(order[start:start + size])


def _mean_psnr(prediction: torch.Tensor, target: torch.Tensor, to_linear: Transform, psnr) -> list[float]:
    """PSNR of every example (linear, clipped to [0, 1] by ``psnr``), as a list."""
    prediction = to_linear(prediction.detach()).permute(0, 2, 3, 1).numpy()
    target = to_linear(target).permute(0, 2, 3, 1).numpy()
    return [min(psnr(p, t), 100.0) for p, t in zip(prediction, target, strict=True)]


def evaluate(model: nn.Module, dataset_split: tuple[torch.Tensor, torch.Tensor], loss_fn: nn.Module | None = None,
             to_linear: Transform = _identity, psnr: Callable | None = None) -> dict[str, float]:
    """Loss and image metrics of ``model`` on one split.

    Parameters
    ----------
    model : nn.Module
    dataset_split : (inputs, targets)
        Tensors (N, C_in, H, W) and (N, C_out, H, W) in the network's space.
    loss_fn : nn.Module, optional
        Adds ``loss`` (mean over examples) when given.
    to_linear : callable
        Network space -> linear values (e.g. :func:`reconstruction.hdr.decode`).
    psnr : callable, optional
        ``psnr(test, reference)`` on (H, W, C) arrays; default :func:`reconstruction.metrics.psnr`.

    Returns
    -------
    dict
        ``psnr`` (mean over examples, dB, capped at 100), ``rmse`` (root of the mean
        squared error of the linear images clipped to [0, 1]), ``loss`` if ``loss_fn``,
        and ``count``.
    """
    psnr = _default_psnr() if psnr is None else psnr
    inputs, targets = dataset_split
    if len(inputs) == 0 or len(inputs) != len(targets):
        raise ValueError(f"need matching, non-empty inputs and targets, got {len(inputs)} and {len(targets)}")
    was_training = model.training
    model.eval()
    loss_sum, psnrs, squared = 0.0, [], 0.0
    with torch.no_grad():
        for index in _batches(len(inputs), EVAL_BATCH):
            prediction = model(inputs[index])
            if loss_fn is not None:
                loss_sum += float(loss_fn(prediction, targets[index])) * len(index)
            psnrs += _mean_psnr(prediction, targets[index], to_linear, psnr)
            difference = to_linear(prediction).clamp(0, 1) - to_linear(targets[index]).clamp(0, 1)
            squared += float((difference ** 2).mean(dim=(1, 2, 3)).sum())
    model.train(was_training)
    metrics = {"psnr": float(np.mean(psnrs)), "rmse": float(np.sqrt(squared / len(inputs))), "count": len(inputs)}
    if loss_fn is not None:
        metrics["loss"] = loss_sum / len(inputs)
    return metrics


def resolve_precision(requested: str) -> tuple[str, str]:
    """The training arithmetic ``"fp32"`` or ``"bf16"`` for a profile's ``precision``, and a note.

    ``"auto"`` is bf16 when the CPU has AVX512-BF16 or AMX tiles (where bf16 matrix products
    run in hardware), else fp32; the note says which and why ("" when nothing was decided).
    """
    from reconstruction.inference import _bf16_supported

    if requested == "auto":
        if _bf16_supported():
            return "bf16", "bf16 mixed precision (the CPU has AVX512-BF16/AMX)"
        return "fp32", "fp32: the CPU has neither AVX512-BF16 nor AMX, so bf16 autocast would be emulated (slow)"
    if requested not in ("fp32", "bf16"):
        raise ValueError(f"precision must be 'fp32', 'bf16' or 'auto', got {requested!r}")
    return requested, ""


def _forward(model: nn.Module, inputs: torch.Tensor, precision: str) -> torch.Tensor:
    """``model(inputs)``; under bf16 autocast in channels-last layout, returned as fp32 (the loss runs in fp32)."""
    if precision != "bf16":
        return model(inputs)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        prediction = model(inputs.contiguous(memory_format=torch.channels_last))
    return prediction.float().contiguous()


def learning_rate_factor(step: int, warmup_steps: int, decay: str, total_steps: int) -> float:
    """Multiplier of the peak learning rate at Adam step ``step`` (0-based); see :func:`fit`."""
    factor = min(1.0, (step + 1) / warmup_steps) if warmup_steps else 1.0
    if decay == "cosine":
        factor *= 0.5 * (1.0 + math.cos(math.pi * min(step, total_steps) / total_steps))
    return factor


def fit(model: nn.Module, loss_fn: nn.Module, data: dict[str, tuple[torch.Tensor, torch.Tensor]], directory: Path,
        data_hash: str, epochs: int, batch_size: int, learning_rate: float, seed: int,
        to_linear: Transform = _identity, psnr: Callable | None = None, progress: bool | None = None,
        precision: str = "fp32", patience: int = 0, warmup_steps: int = 0, decay: str = "constant") -> TrainResult:
    """Train ``model`` with Adam, resuming from ``directory/checkpoint.pt`` when it matches.

    Parameters
    ----------
    model : nn.Module
        Freshly initialised (its weights are replaced on resume).
    loss_fn : nn.Module
        ``loss_fn(prediction, target)`` -> scalar, in the network's space.
    data : dict
        ``"train"`` and ``"validation"`` -> (inputs, targets) tensors, (N, C, H, W).
    directory : Path
        Where checkpoints, history and plot go.
    data_hash : str
        Identity of ``data``; a checkpoint with another hash is not resumed (ValueError).
    epochs, batch_size : int
    learning_rate : float
    seed : int
        Seeds the shuffling generator (NumPy) and torch's RNG.
    to_linear : callable
        Network space -> linear values, for PSNR.
    psnr : callable, optional
        ``psnr(test, reference)`` on (H, W, C) arrays; default :func:`reconstruction.metrics.psnr`.
    progress : bool, optional
        Show a tqdm bar over epochs (None: only on a terminal).
    precision : {"fp32", "bf16"}
        Training arithmetic (see :func:`resolve_precision`); bf16 keeps fp32 master weights and
        Adam state and computes the loss in fp32. Validation is always fp32.
    patience : int
        Stop after this many epochs without a lower validation loss (0: never early).
    warmup_steps : int
        The learning rate rises linearly over the first ``warmup_steps`` Adam steps,
        ``learning_rate * min(1, (step + 1) / warmup_steps)`` (0: none). The step is counted from
        the epoch and batch, so a resumed training continues the same schedule.
    decay : {"constant", "cosine"}
        ``"cosine"`` multiplies that rate by ``(1 + cos(pi * step / total)) / 2``, ``total``
        being all the Adam steps of ``epochs`` epochs: from the full rate down to 0 at the end.

    Returns
    -------
    TrainResult
    """
    psnr = _default_psnr() if psnr is None else psnr
    if warmup_steps < 0:
        raise ValueError(f"warmup_steps must be >= 0, got {warmup_steps}")
    if precision not in ("fp32", "bf16"):
        raise ValueError(f"precision must be 'fp32' or 'bf16' (resolve 'auto' first), got {precision!r}")
    if decay not in DECAYS:
        raise ValueError(f"decay must be one of {DECAYS}, got {decay!r}")
    for split in ("train", "validation"):
        if split not in data or len(data[split][0]) == 0:
            raise ValueError(f"the {split} split is empty")
    directory = Path(directory)
    checkpoint_path = directory / "checkpoint.pt"
    optimizer = torch.optim.Adam(model.parameters(), lr=learning_rate)
    rng = np.random.default_rng(seed)
    torch.manual_seed(seed)
    history: list[dict[str, float]] = []
    best = {"loss": float("inf"), "epoch": 0, "state": copy.deepcopy(model.state_dict())}
    if checkpoint_path.is_file():
        state = load_checkpoint(checkpoint_path, model)
        if state["data_hash"] != data_hash:
            raise ValueError(f"{checkpoint_path} was trained on data {state['data_hash'][:12]}, not {data_hash[:12]}; "
                             "use another directory")
        optimizer.load_state_dict(state["optimizer"])
        rng.bit_generator.state = json.loads(state["numpy_rng"])
        torch.set_rng_state(state["torch_rng"])
        history = json.loads(state["history"])
        best = {"loss": state["best_loss"], "epoch": state["best_epoch"], "state": state["best"]}
    inputs, targets = data["train"]
    steps_per_epoch = math.ceil(len(inputs) / batch_size)
    total_steps = epochs * steps_per_epoch
    bar = tqdm(total=epochs, initial=len(history), unit="epoch", desc=f"train {architecture(model)['architecture']}",
               disable=None if progress is None else not progress, leave=False)
    if precision == "bf16":
        model.to(memory_format=torch.channels_last)
    for epoch in range(len(history) + 1, epochs + 1):
        if patience and epoch - 1 - best["epoch"] >= patience:
            break  # early stopping (also on resume: the history already shows it)
        started = time.perf_counter()
        model.train()
        loss_sum, psnrs = 0.0, []
        first_step = (epoch - 1) * steps_per_epoch
        for step, index in enumerate(_batches(len(inputs), batch_size, rng.permutation(len(inputs))), first_step):
            for group in optimizer.param_groups:  # factor 1 without warm-up and decay: the rate as given
                group["lr"] = learning_rate * learning_rate_factor(step, warmup_steps, decay, total_steps)
            prediction = _forward(model, inputs[index], precision)
            loss = loss_fn(prediction, targets[index])
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            loss_sum += float(loss.detach()) * len(index)
            psnrs += _mean_psnr(prediction, targets[index], to_linear, psnr)
        validation = evaluate(model, data["validation"], loss_fn, to_linear, psnr)
        history.append({"epoch": epoch, "train_loss": loss_sum / len(inputs), "validation_loss": validation["loss"],
                         "train_psnr": float(np.mean(psnrs)), "validation_psnr": validation["psnr"],
                         "seconds": time.perf_counter() - started})
        if validation["loss"] < best["loss"]:
            best = {"loss": validation["loss"], "epoch": epoch, "state": copy.deepcopy(model.state_dict())}
            best_model = copy.deepcopy(model)
            best_model.load_state_dict(best["state"])
            save_checkpoint(directory / "best.pt", best_model, data_hash, epoch=epoch, validation_loss=best["loss"])
        save_checkpoint(checkpoint_path, model, data_hash, optimizer=optimizer.state_dict(), epoch=epoch,
                        numpy_rng=json.dumps(rng.bit_generator.state), torch_rng=torch.get_rng_state(),
                        history=json.dumps(history), best=best["state"], best_loss=best["loss"],
                        best_epoch=best["epoch"])
        stopping = patience and epoch - best["epoch"] >= patience
        _write_history(directory, history, plot=epoch == epochs or epoch % PLOT_EVERY == 0 or bool(stopping))
        bar.update(1)
        bar.set_postfix(train=f"{history[-1]['train_loss']:.4g}", val=f"{validation['loss']:.4g}")
    bar.close()
    model.load_state_dict(best["state"])
    model.to(memory_format=torch.contiguous_format)
    model.eval()
    return TrainResult(model, history, best["epoch"], directory, data_hash)


# ------------------------------------------------------------------ entry points
def _training_dir(kind: str, model: nn.Module, loss_fn: nn.Module, data_hash: str,
                  profile: ReconstructionProfile, learning_rate: float, warmup_steps: int = 0,
                  decay: str = "constant") -> Path:
    # the loss is part of the identity: the same net and data trained on another loss is another model
    loss = getattr(loss_fn, "config", None) or type(loss_fn).__name__
    # the training arithmetic is provenance, not identity: a committed network must be found on
    # every machine kind, whichever precision that machine would train in
    # warm-up and decay enter only when used (earlier models keep their keys); a decay's schedule
    # depends on the epoch count, so with one raising `epochs` is another model, not a resume
    key = content_key(kind, architecture(model), parameter_count(model), loss, data_hash, profile.batch_size,
                      learning_rate, profile.seed,
                      *(["warmup", warmup_steps] if warmup_steps else []),
                      *(["decay", decay, profile.epochs] if decay != "constant" else []))
    return cache_root() / "models" / f"{kind}-{key[:24]}"


def model_store_root(profile: ReconstructionProfile) -> Path | None:
    """The folder of the profile's ``model_store`` (None: no store).

    A relative ``model_store`` is relative to the repository (so that the committed networks are
    found whatever the working directory).
    """
    return MODEL_STORE_ROOT / profile.model_store if profile.model_store else None


def _store_dir(directory: Path, profile: ReconstructionProfile) -> Path | None:
    """Where the profile's ``model_store`` keeps the model trained in ``directory`` (None: no store)."""
    root = model_store_root(profile)
    return None if root is None else root / Path(directory).name


def _published_result(model: nn.Module, directory: Path, profile: ReconstructionProfile,
                      data_hash: str) -> TrainResult | None:
    """The finished model of ``directory`` from the profile's ``model_store``, loaded into ``model``.

    None when the profile has no store or the store has no finished copy of it. The stored copy
    wins over a training of the same key in the cache. It must be of the same architecture
    (:func:`load_checkpoint`) and data, else ValueError.
    """
    store = _store_dir(directory, profile)
    if store is None or not (store / "result.json").is_file():
        return None
    state = load_checkpoint(store / "best.pt", model)
    if state["data_hash"] != data_hash:
        raise ValueError(f"{store / 'best.pt'} was trained on data {state['data_hash'][:12]}, not {data_hash[:12]}")
    model.eval()
    return TrainResult(model, json.loads((store / "history.json").read_text()), int(state["epoch"]), store, data_hash)


def _publish(result: TrainResult, profile: ReconstructionProfile) -> None:
    """Copy a finished model's :data:`PUBLISHED_FILES` to the profile's ``model_store`` (atomically each).

    Once: a stored copy is kept as it is, so reusing the cached model (whose ``result.json`` is
    written again with a new provenance stamp) does not rewrite committed files.
    """
    store = _store_dir(result.directory, profile)
    if store is None or (store / "result.json").is_file():
        return
    for name in PUBLISHED_FILES:
        if (result.directory / name).is_file():
            atomic_write_bytes(store / name, (result.directory / name).read_bytes())


def denoiser_tensors(dataset_crops: dict[str, np.ndarray], auxiliary: tuple[str, ...] = ("albedo",),
                     encode: Transform | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Network inputs and targets from crops of :func:`reconstruction.data.crops`.

    Parameters
    ----------
    dataset_crops : dict
        ``noisy``, ``reference`` and the ``auxiliary`` buffers, float32 (N, C, H, W).
    auxiliary : tuple of str
        Buffers stacked after the noisy RGB (the order :class:`reconstruction.models.Denoiser` expects).
    encode : callable, optional
        HDR transform of radiance and depth; default :func:`reconstruction.hdr.encode`.

    Returns
    -------
    inputs : torch.Tensor, (N, 3 + aux channels, H, W)
        encode(noisy), then the auxiliary buffers (depth encoded, the others as rendered).
    targets : torch.Tensor, (N, 3, H, W)
        encode(reference).
    """
    if encode is None:
        from reconstruction.hdr import encode
    planes = [encode(torch.from_numpy(dataset_crops["noisy"]))]
    for name in auxiliary:
        plane = torch.from_numpy(dataset_crops[name])
        planes.append(encode(plane) if name == "depth" else plane)
    return torch.cat(planes, dim=1), encode(torch.from_numpy(dataset_crops["reference"]))


def _datasets(scene_names: list[str] | tuple[str, ...], profile: ReconstructionProfile,
              progress: bool | None) -> dict:
    """Scene name -> its dataset, generated or found (once per training: each call loads the scene)."""
    from reconstruction.data import generate_dataset

    if not scene_names:
        raise ValueError("no scenes given")
    return {name: generate_dataset(name, profile, progress) for name in scene_names}


def _dataset_keys(scene_names: list[str] | tuple[str, ...], profile: ReconstructionProfile) -> dict[str, str]:
    """Scene name -> the content key of its dataset, without generating it (a stored model needs no data)."""
    from kdtrace.scenes import load_scene
    from reconstruction.data import dataset_key

    if not scene_names:
        raise ValueError("no scenes given")
    return {name: dataset_key(load_scene(name), profile) for name in scene_names}


def _denoiser_data_hash(keys: dict[str, str], profile: ReconstructionProfile, auxiliary: tuple[str, ...]) -> str:
    """Content key of the crops :func:`_denoiser_crops` draws: dataset keys (by scene) and crop settings."""
    # only scenes with their own count add it: every other model keeps its key (and its cache)
    own_counts = {name: profile.crops_for(name) for name in keys
                  if profile.crops_for(name) != profile.crops_per_view}
    return content_key("denoiser-data", list(keys.values()), list(auxiliary),
                       profile.crop_size, profile.crops_per_view, profile.seed, *([own_counts] if own_counts else []))


def _denoiser_crops(datasets: dict, profile: ReconstructionProfile, auxiliary: tuple[str, ...],
                    encode: Transform | None = None) -> dict[str, tuple[torch.Tensor, torch.Tensor]]:
    """Split -> (inputs, targets) over every dataset's crops, concatenated in scene order."""
    from reconstruction.data import SPLITS, crops

    data = {}
    for split in SPLITS:
        parts = [denoiser_tensors(crops(dataset, split, profile.crop_size, profile.crops_for(name), profile.seed),
                                  auxiliary, encode)
                 for name, dataset in datasets.items()]
        data[split] = (torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts]))
    return data


def denoiser_data(scene_names: list[str] | tuple[str, ...], profile: str | ReconstructionProfile = "quick",
                  auxiliary: tuple[str, ...] = ("albedo",), encode: Transform | None = None,
                  progress: bool | None = None) -> tuple[dict[str, tuple[torch.Tensor, torch.Tensor]], str]:
    """Train / validation / test tensors over the datasets of ``scene_names`` and their hash.

    Returns
    -------
    data : dict
        Split -> (inputs, targets), see :func:`denoiser_tensors`; crops of all scenes concatenated.
    data_hash : str
        Content key of the dataset keys and crop settings.
    """
    profile = resolve_profile(profile)
    datasets = _datasets(scene_names, profile, progress)
    keys = {name: dataset.key for name, dataset in datasets.items()}
    return _denoiser_crops(datasets, profile, auxiliary, encode), _denoiser_data_hash(keys, profile, auxiliary)


def default_denoiser_loss(model: nn.Module, range_floor: float) -> nn.Module:
    """The paper's loss of a denoiser (:class:`reconstruction.loss.EdgeAwareLoss`, σ = 1.4), taken in
    the net's perceptual transfer when it has one (``Denoiser(perceptual=G)``), else in ``log1p``.

    Parameters
    ----------
    model : nn.Module
        The denoiser.
    range_floor : float
        The edge maps' range floor (the profile's ``denoiser_edge_range_floor``).
    """
    from reconstruction.loss import DENOISER_SIGMA, EdgeAwareLoss, InSpace
    from reconstruction.models import to_perceptual

    loss = EdgeAwareLoss(DENOISER_SIGMA, range_floor)
    if getattr(model, "perceptual", 0):  # the loss where the net works, not in log1p
        return InSpace(loss, lambda z: to_perceptual(z, model.radiance_gain, model.perceptual),
                       "perceptual transfer of the net")
    return loss


def train_denoiser(scene_names: list[str] | tuple[str, ...], profile: str | ReconstructionProfile = "quick",
                   model: nn.Module | None = None, loss_fn: nn.Module | None = None,
                   auxiliary: tuple[str, ...] = ("albedo",), directory: Path | None = None,
                   psnr: Callable | None = None, progress: bool | None = None,
                   demodulate: bool = False, warmup_steps: int = 0, perceptual: float = 0.0) -> TrainResult:
    """Train the denoiser on the Precision Graphics datasets of ``scene_names``.

    One scene gives the scene's specialised (Precision Graphics) model, several the
    mixed model. Datasets are generated or reused first.

    Parameters
    ----------
    scene_names : sequence of str
    profile : str or ReconstructionProfile
        Dataset, crop and training settings; trained for its ``denoiser_epochs`` (else ``epochs``;
        the mixed model is given :attr:`ReconstructionProfile.mixed`).
    model : nn.Module, optional
        Default :class:`reconstruction.models.Denoiser` with ``auxiliary`` and
        ``demodulate``, initialised after ``torch.manual_seed(profile.seed)``.
    loss_fn : nn.Module, optional
        Default :class:`reconstruction.loss.EdgeAwareLoss` (sigma 1.4, the profile's
        ``denoiser_edge_range_floor``).
    auxiliary : tuple of str
        Buffers after the noisy RGB in the input.
    directory : Path, optional
        Default ``cache_root()/models/denoiser-<key>``.
    psnr : callable, optional
        Default :func:`reconstruction.metrics.psnr`.
    progress : bool, optional
    demodulate : bool
        The default model denoises the albedo-demodulated colour (the documented variant of
        :class:`reconstruction.models.Denoiser`); ignored when ``model`` is given.
    perceptual : float
        The default model works in the perceptual transfer with this gain G (0: the paper's
        ``log1p`` space; :class:`reconstruction.models.Denoiser`), is calibrated on the training
        targets, and the loss is taken in that space; ignored when ``model`` is given.
    warmup_steps : int
        Learning-rate warm-up of :func:`fit` for this model (a variant's own); the longer of it
        and the profile's ``denoiser_warmup_steps`` is used (part of the cache key when not 0).
        The peak rate and its decay are the profile's ``denoiser_rate`` and ``denoiser_decay``.

    Returns
    -------
    TrainResult
        Also writes ``result.json`` (test metrics of the kept weights, settings, provenance) and
        copies the model to the profile's ``model_store``. A model found there finished (and not in
        the cache) is returned as it is, untrained, with the store's folder as its ``directory``.
    """
    from reconstruction.hdr import decode

    profile = resolve_profile(profile).denoiser
    data_hash = _denoiser_data_hash(_dataset_keys(scene_names, profile), profile, auxiliary)
    if model is None:
        from reconstruction.models import Denoiser

        torch.manual_seed(profile.seed)
        model = Denoiser(auxiliary, demodulate=demodulate, perceptual=perceptual)
    if loss_fn is None:
        loss_fn = default_denoiser_loss(model, profile.denoiser_edge_range_floor)
    warmup_steps = max(warmup_steps, profile.denoiser_warmup_steps)
    schedule = {"warmup_steps": warmup_steps, "learning_rate": profile.denoiser_rate, "decay": profile.denoiser_decay}
    if directory is None:
        directory = _training_dir("denoiser", model, loss_fn, data_hash, profile, **schedule)
    directory = Path(directory)
    with claim(directory):  # a second process on this cache waits for this training instead of running it too
        published = _published_result(model, directory, profile, data_hash)
        if published is not None:
            return published  # no dataset is generated and no crop drawn: the mixed model's take about 10 GB
        datasets = _datasets(scene_names, profile, progress)
        data = _denoiser_crops(datasets, profile, auxiliary)
        if getattr(model, "perceptual", 0):
            model.calibrate(data["train"][1])
        precision = resolve_precision(profile.precision)[0]
        result = fit(model, loss_fn, data, directory, data_hash, profile.epochs, profile.batch_size,
                     profile.denoiser_rate, profile.seed, decode, psnr, progress, precision, profile.patience,
                     warmup_steps, profile.denoiser_decay)
        _write_result(result, evaluate(result.model, data["test"], loss_fn, decode, psnr), list(scene_names),
                      profile, **schedule)
        _publish(result, profile)
        return result


def superres_tensors(pairs: dict[str, np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    """BT.601 luma of the input and target RGB crops of :func:`reconstruction.data.superres_data`.

    Returns
    -------
    inputs, targets : torch.Tensor, (N, 1, H, W)
        Y of the bicubic-upsampled input and of the target, in [0, 1].
    """
    from reconstruction.models import ycbcr_from_rgb

    return tuple(ycbcr_from_rgb(torch.from_numpy(pairs[name]), channel_axis=-3)[:, :1].contiguous()
                 for name in ("input", "target"))


def train_superres(profile: str | ReconstructionProfile = "quick", scene_names: list[str] | tuple[str, ...] = (),
                   model: nn.Module | None = None, loss_fn: nn.Module | None = None, directory: Path | None = None,
                   psnr: Callable | None = None, progress: bool | None = None, space: str = "linear") -> TrainResult:
    """Train the Y-channel superresolution network on photo crops plus renders of ``scene_names``.

    Parameters
    ----------
    profile : str or ReconstructionProfile
    scene_names : sequence of str
        Scenes whose datasets add render crops (their test views form the test split).
    model : nn.Module, optional
        Default :class:`reconstruction.models.Superresolution` (seeded initialisation).
    loss_fn : nn.Module, optional
        Default :class:`reconstruction.loss.EdgeAwareLoss` with sigma 1.
    directory, psnr, progress
        As for :func:`train_denoiser`.
    space : {"linear", "display"}
        The image space of the crops (:func:`reconstruction.data.superres_data`) and of the default
        model (:class:`reconstruction.models.Superresolution`); a given ``model``'s own ``space`` wins.

    Returns
    -------
    TrainResult
        ``result.json`` holds the test metrics (renders) when scenes are given, and
        those of the bicubic input for comparison; the profile's ``model_store`` as for
        :func:`train_denoiser`.
    """
    from reconstruction.data import AUGMENT_EXPOSURE, AUGMENT_FACTOR, generate_dataset, superres_data

    profile = resolve_profile(profile)
    if model is None:
        from reconstruction.models import Superresolution

        torch.manual_seed(profile.seed)
        model = Superresolution(space)
    space = getattr(model, "space", space)
    keys = list(_dataset_keys(scene_names, profile).values()) if scene_names else []
    data_hash = content_key("superres-data", keys, profile.superres_crop_size,
                            profile.superres_crops_per_image, profile.superres_downsample, profile.seed,
                            *(["augmented", AUGMENT_FACTOR, AUGMENT_EXPOSURE] if profile.superres_augment else []),
                            *(["space", space] if space != "linear" else []))
    if loss_fn is None:
        from reconstruction.loss import SUPERRESOLUTION_SIGMA, EdgeAwareLoss

        loss_fn = EdgeAwareLoss(SUPERRESOLUTION_SIGMA)
    directory = (_training_dir("superres", model, loss_fn, data_hash, profile, profile.learning_rate)
                 if directory is None else Path(directory))
    with claim(directory):  # as train_denoiser's
        published = _published_result(model, directory, profile, data_hash)
        if published is not None:
            return published
        datasets = [generate_dataset(name, profile, progress) for name in scene_names]
        data = {split: superres_tensors(value) for split, value in superres_data(profile, datasets, space).items()}
        precision = resolve_precision(profile.precision)[0]
        result = fit(model, loss_fn, data, directory, data_hash, profile.epochs, profile.batch_size,
                     profile.learning_rate, profile.seed, _identity, psnr, progress, precision, profile.patience)
        if "test" in data:
            metrics = evaluate(result.model, data["test"], loss_fn, _identity, psnr)
            metrics["bicubic"] = evaluate(nn.Identity(), data["test"], loss_fn, _identity, psnr)
            _write_result(result, metrics, list(scene_names), profile, profile.learning_rate)
            _publish(result, profile)  # result.json marks a finished copy: without a test split nothing is stored
        return result


def _write_result(result: TrainResult, test: dict[str, Any], scenes: list[str], profile: ReconstructionProfile,
                  learning_rate: float, warmup_steps: int = 0, decay: str = "constant") -> None:
    """``result.json``: test metrics of the kept weights, best epoch, data hash, settings, provenance."""
    precision, note = resolve_precision(profile.precision)
    record = {"scenes": scenes, "test": test, "best_epoch": result.best_epoch, "epochs_run": len(result.history),
              "precision": precision, "precision_note": note, "warmup_steps": warmup_steps,
              "learning_rate": learning_rate, "decay": decay,
              "data_hash": result.data_hash,
              **architecture(result.model), "parameters": parameter_count(result.model),
              "provenance": stamp(dataclasses.asdict(profile))}
    atomic_write_bytes(result.directory / "result.json", json.dumps(record, indent=1).encode())
