"""The paper's Figures 4-8 as PNG panels for the report.

* Figure 4, :func:`training_curves`: loss and PSNR per epoch of each network, train
  (solid) and validation (dashed), one colour per model.
* Figures 5-6, :func:`denoising_panel`: noisy input, denoisers and reference side by
  side, PSNR under each, with an enlarged crop of one region below.
* Figure 7, :func:`superres_panel`: the half-resolution input, bicubic, our
  superresolution and the reference, the same way.
* Figure 8, :func:`pipeline_panel`: the §6.4 stages and, beside them, the tiled-minus-
  whole-frame difference of the denoiser (:func:`pipeline_stages` computes both).
* :func:`scene_figures` makes the Figures 5 and 7 panels of one scene from its dataset,
  :func:`markdown_links` the report's image links.
* :func:`write_linear_strip` saves the linear images of one scene's comparison strip as
  EXR for the verdict page (:mod:`reports.verdict`), on the view :func:`strip_view` picks.

Display convention (every image panel of a comparison): the tables' display-referred
tonemapping (:mod:`reconstruction.metrics`): linear radiance times the exposure that maps the
reference's 99th-percentile luminance to 1 (one exposure per figure; 1 when the reference is
all black), NaN/inf replaced (display only, with a warning), clipped to [0, 1], then the sRGB
transfer curve. So a figure shows what its numbers measure. Under each panel: the display
PSNR of that image (the paper's space) and the linear PSNR (clipped to [0, 1]); an image with
non-finite values gets none. They are PSNRs of the one image shown, not the pooled PSNRs over
a split that the tables report.

**Crop rule.** Unless a crop is given, the enlarged region is the square window (side a
quarter of the smaller image side, at least 8 pixels or the whole side) holding the most
*reference* detail: the largest sum of squared horizontal and vertical differences of the
display-encoded reference luma (BT.709 weights); ties go to the first window in row-major
order. It depends on the reference alone, never on any method's output, so it is not
picked where our networks look best (nor where the noisy input is worst, which is
mostly where the radiance is brightest); edges and shadow boundaries are where denoisers
blur.

**View rule** (:func:`scene_figures`): the first test view in sorted name order, unless a
view is named; never chosen by its results. The verdict page's strips use
:func:`strip_view` instead, which skips mostly black views; it too looks at the references only.

Figures are drawn at :data:`DPI` dots per inch on matplotlib's Agg canvas (no pyplot
state), about :data:`PANEL_INCHES` inches per panel, and written atomically as PNG. A file
over :data:`MAX_PNG_BYTES` is re-encoded with a 256-colour palette, then a 64-colour one
(they are committed to git; measured: a 5-panel row of 512x512 white noise needed 64); if
still too big, a warning says so.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from kdtrace.cache import atomic_write_bytes
from kdtrace.imageio import srgb_encode

#: Resolution of every figure, dots per inch.
DPI = 100
#: Width and height of one image panel (one row), inches.
PANEL_INCHES = 3.0
#: Largest PNG kept as full colour, bytes; larger ones are palette-encoded.
MAX_PNG_BYTES = 500_000
#: Palette sizes tried in turn for a PNG over :data:`MAX_PNG_BYTES`.
PALETTES = (256, 64)
#: Side of the automatic crop as a fraction of the smaller image side.
CROP_FRACTION = 0.25
#: Smallest automatic crop side, pixels (or the whole side of a smaller image).
MIN_CROP = 8
#: BT.709 luma weights of linear RGB (used on display-encoded values for the crop rule).
LUMA = np.array([0.2126, 0.7152, 0.0722])
#: History columns :func:`training_curves` plots.
HISTORY_KEYS = ("epoch", "train_loss", "validation_loss", "train_psnr", "validation_psnr")
#: Colour of the crop rectangle.
CROP_COLOUR = "#ffd400"
#: A reference pixel counts as lit for :func:`strip_view` when its exposed luminance (luminance
#: times the view's exposure, display white = 1) is at least this.
LIT_FRACTION = 0.05
#: Folder of the verdict page's linear strip images inside a results folder.
STRIP_FOLDER = "verdict"
#: Name of the file that describes one scene's saved strip (:func:`write_linear_strip`).
STRIP_MANIFEST = "strip.json"

#: A crop rectangle in pixels: (top, left, height, width).
Crop = tuple[int, int, int, int]


@dataclass(frozen=True)
class Panel:
    """A written comparison figure and the numbers printed on it.

    Usable wherever a path is (``os.fspath(panel)`` is its file).

    Attributes
    ----------
    path : Path
        The PNG file.
    psnr : dict
        Panel name -> PSNR against the reference, dB (:func:`reconstruction.metrics.psnr`;
        ``inf`` for an identical image, NaN when not computed).
    labels : dict
        Panel name -> the text written under it.
    crop : tuple of int or None
        The enlarged region (top, left, height, width), pixels; None without a crop row.
    extras : dict
        Other printed numbers, e.g. ``difference_max`` of :func:`pipeline_panel`.
    """

    path: Path
    psnr: dict[str, float]
    labels: dict[str, str]
    crop: Crop | None = None
    extras: dict[str, float] = field(default_factory=dict)

    def __fspath__(self) -> str:
        return os.fspath(self.path)


# ------------------------------------------------------------------ arrays
def as_rgb(image: Any, name: str) -> np.ndarray:
    """An image as float64 (H, W, 3): (H, W) and (H, W, 1) are repeated to three channels.

    Raises
    ------
    ValueError
        Not 2-D or (H, W, 1|3), or empty.
    """
    array = np.asarray(image, dtype=np.float64)
    if array.ndim == 2:
        array = array[:, :, None]
    if array.ndim != 3 or array.shape[2] not in (1, 3):
        raise ValueError(f"{name} must have shape (H, W), (H, W, 1) or (H, W, 3), got {np.shape(image)}")
    if array.size == 0:
        raise ValueError(f"{name} is empty: {array.shape}")
    return np.repeat(array, 3, axis=2) if array.shape[2] == 1 else array


def _check_shapes(images: Mapping[str, np.ndarray], shape: tuple[int, ...], what: str) -> None:
    for name, image in images.items():
        if image.shape != shape:
            raise ValueError(f"image {name!r} has shape {image.shape[:2]} but {what} has {shape[:2]}")


def display(image: Any, name: str = "image", exposure: float = 1.0) -> np.ndarray:
    """The displayed values of a linear image: finite, times ``exposure``, clipped to [0, 1], sRGB-encoded.

    NaN becomes 0, +inf 1 and -inf 0, with a ``RuntimeWarning`` naming the image and the
    count (for display only: no PSNR is computed for such an image).

    Parameters
    ----------
    image : array_like
        (H, W), (H, W, 1) or (H, W, 3) linear radiance (any non-negative scale; values
        above 1 saturate).
    name : str
        Used in the warning.

    Returns
    -------
    numpy.ndarray
        (H, W, 3) float64 sRGB-encoded values in [0, 1].
    """
    array = as_rgb(image, name)
    bad = int(np.count_nonzero(~np.isfinite(array)))
    if bad:
        warnings.warn(f"{name}: {bad} NaN/inf values replaced for display (NaN and -inf -> 0, +inf -> 1)",
                      RuntimeWarning, stacklevel=2)
        array = np.nan_to_num(array, nan=0.0, posinf=1.0, neginf=0.0)
    return srgb_encode(np.clip(array * exposure, 0.0, 1.0))


def figure_exposure(reference: np.ndarray) -> float:
    """The display exposure of a figure: :func:`reconstruction.metrics.auto_exposure` of its reference,
    1 when the reference is all black or not finite (then nothing is exposed)."""
    from reconstruction.metrics import auto_exposure

    try:
        return auto_exposure(reference)
    except ValueError:
        return 1.0


def panel_psnr(image: np.ndarray, reference: np.ndarray, exposure: float | None = None) -> float:
    """PSNR of ``image`` against ``reference``, dB: linear clipped to [0, 1] (:func:`reconstruction.metrics.psnr`),
    or of the displayed images with ``exposure``; NaN if either is non-finite."""
    from reconstruction.metrics import psnr, to_display

    if not (np.all(np.isfinite(image)) and np.all(np.isfinite(reference))):
        return math.nan
    if exposure is None:
        return psnr(image, reference)
    return psnr(to_display(image, exposure), to_display(reference, exposure))


def psnr_label(value: float, display_value: float | None = None) -> str:
    """The text under a panel: ``"PSNR 31.42 dB"`` (linear), with the display PSNR first when given
    (``"display 24.10 dB · linear 31.42 dB"``), ``"PSNR inf dB (identical)"`` or ``"PSNR n/a (non-finite)"``."""
    if math.isnan(value):
        return "PSNR n/a (non-finite)"
    if math.isinf(value):
        return "PSNR inf dB (identical)"
    if display_value is None:
        return f"PSNR {value:.2f} dB"
    return f"display {display_value:.2f} dB · linear {value:.2f} dB"


def detail_energy(reference: Any) -> np.ndarray:
    """Per-pixel detail of a reference: squared right and down differences of its displayed luma.

    Returns
    -------
    numpy.ndarray
        (H, W) float64; the last row has no down difference and the last column no right one.
    """
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # non-finite values are warned about where displayed
        luma = display(reference, "reference") @ LUMA
    energy = np.zeros_like(luma)
    energy[:, :-1] += np.diff(luma, axis=1) ** 2
    energy[:-1, :] += np.diff(luma, axis=0) ** 2
    return energy


def crop_side(height: int, width: int, fraction: float = CROP_FRACTION) -> int:
    """Side of the automatic crop, pixels: ``fraction`` of the smaller side, at least :data:`MIN_CROP` (or the side)."""
    smaller = min(height, width)
    return max(1, min(smaller, max(int(smaller * fraction), MIN_CROP)))


def auto_crop(reference: Any, fraction: float = CROP_FRACTION) -> Crop:
    """The square window with the most reference detail (the module's crop rule).

    Parameters
    ----------
    reference : array_like
        (H, W[, C]) linear reference image.
    fraction : float
        Window side as a fraction of the smaller image side (see :func:`crop_side`).

    Returns
    -------
    tuple of int
        (top, left, side, side) in pixels, inside the image. Ties (e.g. a flat image) give
        the first window in row-major order.
    """
    energy = detail_energy(reference)
    height, width = energy.shape
    side = crop_side(height, width, fraction)
    table = np.zeros((height + 1, width + 1))
    table[1:, 1:] = energy.cumsum(axis=0).cumsum(axis=1)
    sums = table[side:, side:] - table[:-side, side:] - table[side:, :-side] + table[:-side, :-side]
    top, left = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(top), int(left), side, side


def check_crop(crop: Sequence[int], height: int, width: int) -> Crop:
    """A crop (top, left, height, width) as ints, checked to lie inside an ``height`` x ``width`` image."""
    if len(crop) != 4:
        raise ValueError(f"crop must be (top, left, height, width), got {crop!r}")
    top, left, rows, columns = (int(value) for value in crop)
    if rows < 1 or columns < 1 or top < 0 or left < 0 or top + rows > height or left + columns > width:
        raise ValueError(f"crop {crop!r} is not inside the {height}x{width} image")
    return top, left, rows, columns


def scale_crop(crop: Crop, scale: float, shape: tuple[int, int]) -> Crop:
    """The region of ``crop`` in an image ``scale`` times the size (outward-rounded, inside ``shape``, never empty)."""
    top, left, rows, columns = crop
    first_row, first_column = min(math.floor(top * scale), shape[0] - 1), min(math.floor(left * scale), shape[1] - 1)
    last_row = min(max(math.ceil((top + rows) * scale), first_row + 1), shape[0])
    last_column = min(max(math.ceil((left + columns) * scale), first_column + 1), shape[1])
    return first_row, first_column, last_row - first_row, last_column - first_column


def zoom(image: np.ndarray, crop: Crop, size: int) -> np.ndarray:
    """The crop of ``image`` enlarged by nearest neighbour (integer repetition) to about ``size`` pixels."""
    top, left, rows, columns = crop
    factor = max(1, round(size / max(rows, columns)))
    region = image[top:top + rows, left:left + columns]
    return np.repeat(np.repeat(region, factor, axis=0), factor, axis=1)


# ------------------------------------------------------------------ figures
def _figure(width: float, height: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), dpi=DPI, layout="constrained")


def write_figure(figure, path: str | Path) -> Path:
    """Render ``figure`` on the Agg canvas and write it to ``path`` as PNG, atomically.

    The pixel size is the figure size times :data:`DPI`. Over :data:`MAX_PNG_BYTES` the
    image is palette-encoded (:data:`PALETTES` colours in turn, until it fits); still
    over, a ``RuntimeWarning``.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from PIL import Image

    canvas = FigureCanvasAgg(figure)
    canvas.draw()
    image = Image.fromarray(np.asarray(canvas.buffer_rgba())[:, :, :3].copy())
    data = _png(image)
    for colours in PALETTES:
        if len(data) <= MAX_PNG_BYTES:
            break
        data = _png(image.quantize(colours, method=Image.Quantize.MEDIANCUT))
    if len(data) > MAX_PNG_BYTES:
        warnings.warn(f"{path}: {len(data)} bytes even with a {PALETTES[-1]}-colour palette (limit {MAX_PNG_BYTES})",
                      RuntimeWarning, stacklevel=2)
    return atomic_write_bytes(path, data)


def _png(image) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def _bare(axes) -> None:
    axes.set_xticks([])
    axes.set_yticks([])


def _crop_rectangle(axes, crop: Crop, scale: float = 1.0) -> None:
    from matplotlib.patches import Rectangle

    top, left, rows, columns = crop
    axes.add_patch(Rectangle((left * scale - 0.5, top * scale - 0.5), columns * scale, rows * scale,
                             fill=False, edgecolor=CROP_COLOUR, linewidth=1.5))


def _comparison(panels: dict[str, np.ndarray], labels: dict[str, str], crop: Crop | None, path: str | Path,
                title: str, scales: dict[str, float] | None = None, extra: Callable | None = None) -> Path:
    """One row of displayed images with a label under each, optionally a row of their enlarged crops.

    ``panels`` hold display values; ``scales`` the size of a panel relative to the crop's
    frame (0.5 for a half-size input); ``extra(figure, axes)`` draws into one more column.
    """
    scales = scales or {}
    columns = len(panels) + (extra is not None)
    rows = 2 if crop is not None else 1
    figure = _figure(PANEL_INCHES * columns, PANEL_INCHES * rows + (0.3 if title else 0.0))
    grid = figure.subplots(rows, columns, squeeze=False)
    size = round(PANEL_INCHES * DPI)
    for index, (name, image) in enumerate(panels.items()):
        axes = grid[0, index]
        axes.imshow(image, interpolation="nearest")
        axes.set_title(name, fontsize=10)
        axes.set_xlabel(labels.get(name, ""), fontsize=10)
        _bare(axes)
        if crop is not None:
            scale = scales.get(name, 1.0)
            _crop_rectangle(axes, crop, scale)
            scaled = scale_crop(crop, scale, image.shape[:2])
            below = grid[1, index]
            below.imshow(zoom(image, scaled, size), interpolation="nearest")
            below.set_xlabel("crop, nearest-neighbour zoom", fontsize=8)
            _bare(below)
    if extra is not None:
        extra(figure, grid[0, -1])
        for axes in grid[1:, -1]:
            axes.set_axis_off()
    if title:
        figure.suptitle(title, fontsize=11)
    written = write_figure(figure, path)
    figure.clear()
    return written


def _named_images(images: Mapping[str, Any], what: str) -> dict[str, np.ndarray]:
    if not images:
        raise ValueError(f"{what}: no images given")
    return {str(name): as_rgb(image, f"image {name!r}") for name, image in images.items()}


def _scored(images: dict[str, np.ndarray], reference: np.ndarray,
            exposure: float | None = None) -> tuple[dict[str, float], dict[str, str]]:
    """Linear PSNR per image, and the labels (with the display PSNR first when an ``exposure`` is given)."""
    scores = {name: panel_psnr(image, reference) for name, image in images.items()}
    if exposure is None:
        return scores, {name: psnr_label(value) for name, value in scores.items()}
    shown = {name: panel_psnr(image, reference, exposure) for name, image in images.items()}
    return scores, {name: psnr_label(scores[name], shown[name]) for name in images}


def training_curves(histories: Mapping[str, Sequence[Mapping[str, float]]], path: str | Path) -> Path:
    """Figure 4: loss and PSNR per epoch of each model, train solid and validation dashed.

    One colour per model (matplotlib's ``tab10`` cycle, in the given order); the loss axis
    is logarithmic (the denoiser's and the superresolution net's losses differ in scale); a
    dot marks each model's kept epoch (lowest validation loss, the weights the tables use).

    Parameters
    ----------
    histories : mapping
        Model name (e.g. ``"cbox-original"``, ``"mixed"``, ``"superresolution"``) -> the
        per-epoch rows of :attr:`reconstruction.train.TrainResult.history` (``epoch``,
        ``train_loss``, ``validation_loss``, ``train_psnr``, ``validation_psnr`` in dB).
    path : str or Path
        PNG file (11 x 4 inches).

    Returns
    -------
    Path

    Raises
    ------
    ValueError
        No model, a model without epochs, or rows missing one of :data:`HISTORY_KEYS`.
    """
    from matplotlib.lines import Line2D

    if not histories:
        raise ValueError("training_curves: no histories given")
    for name, history in histories.items():
        if not history:
            raise ValueError(f"history of {name!r} has no epochs")
        missing = sorted({key for row in history for key in HISTORY_KEYS if key not in row})
        if missing:
            raise ValueError(f"history of {name!r} lacks {', '.join(missing)}")
    figure = _figure(11, 4)
    loss_axes, psnr_axes = figure.subplots(1, 2)
    colours = [f"C{index % 10}" for index in range(len(histories))]
    for colour, history in zip(colours, histories.values(), strict=True):
        epochs = [row["epoch"] for row in history]
        for axes, quantity in ((loss_axes, "loss"), (psnr_axes, "psnr")):
            for split, style in (("train", "-"), ("validation", "--")):
                axes.plot(epochs, [row[f"{split}_{quantity}"] for row in history], style, color=colour, linewidth=1.2)
        kept = min(history, key=lambda row: row["validation_loss"])
        loss_axes.plot(kept["epoch"], kept["validation_loss"], "o", color=colour, markersize=4)
        psnr_axes.plot(kept["epoch"], kept["validation_psnr"], "o", color=colour, markersize=4)
    loss_axes.set_yscale("log")
    for axes, label in ((loss_axes, "loss"), (psnr_axes, "PSNR (dB)")):
        axes.set_xlabel("epoch")
        axes.set_ylabel(label)
        axes.grid(alpha=0.3)
    handles = [Line2D([], [], color=colour, label=name) for colour, name in zip(colours, histories, strict=True)]
    handles += [Line2D([], [], color="0.3", linestyle="-", label="train"),
                Line2D([], [], color="0.3", linestyle="--", label="validation"),
                Line2D([], [], color="0.3", marker="o", linestyle="", label="kept epoch")]
    psnr_axes.legend(handles=handles, fontsize=8, loc="lower right")
    written = write_figure(figure, path)
    figure.clear()
    return written


def denoising_panel(images: Mapping[str, Any], reference: Any, path: str | Path, title: str = "",
                    crop: Sequence[int] | None = None, reference_label: str = "reference") -> Panel:
    """Figures 5-6: each image beside the reference, its PSNR under it, and an enlarged crop of each.

    Top row: the images in the given order (e.g. noisy / ours / mixed / OIDN), then the
    reference, displayed as in the module docstring, the crop region outlined; under each
    its PSNR against the reference. Bottom row: the same crop of every panel, enlarged by
    nearest neighbour.

    Parameters
    ----------
    images : mapping
        Panel name -> (H, W[, C]) linear image (the noisy input first: its name is shown).
    reference : array_like
        (H, W[, C]) linear reference.
    path : str or Path
        PNG file (3 inches per panel, 6 inches high, plus 0.3 with a title).
    title : str
        Figure title (e.g. scene and view).
    crop : tuple of int, optional
        (top, left, height, width) in pixels; default :func:`auto_crop` of the reference.
    reference_label : str
        Name of the reference panel, e.g. ``"reference, 64 spp"``.

    Returns
    -------
    Panel
        ``psnr`` and ``labels`` per image (not the reference), and the crop used.

    Raises
    ------
    ValueError
        No image, a shape differing from the reference's, a bad crop, or a name equal to
        ``reference_label``.
    """
    reference = as_rgb(reference, "reference")
    named = _named_images(images, "denoising_panel")
    _check_shapes(named, reference.shape, "the reference")
    if reference_label in named:
        raise ValueError(f"an image is named like the reference panel, {reference_label!r}")
    crop = auto_crop(reference) if crop is None else check_crop(crop, *reference.shape[:2])
    exposure = figure_exposure(reference)
    scores, labels = _scored(named, reference, exposure)
    shown = {name: display(image, name, exposure) for name, image in named.items()}
    shown[reference_label] = display(reference, reference_label, exposure)
    labels_shown = {**labels, reference_label: f"(reference; exposure {exposure:.3g})"}
    written = _comparison(shown, labels_shown, crop, path, title)
    return Panel(written, scores, labels, crop)


def superres_panel(low: Any, bicubic: Any, ours: Any, reference: Any, path: str | Path,
                   crop: Sequence[int] | None = None, title: str = "") -> Panel:
    """Figure 7: the half-size input, bicubic and our 2x upsampling, and the reference, with crops.

    Top row: the input (shown at its own size, drawn as large as the others), bicubic,
    ours and the reference, PSNR under the two upsamplings; bottom row: the same region of
    each enlarged by nearest neighbour (for the input, the region at half scale).

    Parameters
    ----------
    low : array_like
        (H/2, W/2[, C]) the image both upsamplers were given.
    bicubic, ours : array_like
        (H, W[, C]) the upsampled images.
    reference : array_like
        (H, W[, C]) the full-size target (values in [0, 1], as in
        :func:`reconstruction.evaluate.superres_images`).
    path : str or Path
        PNG file (12 x 6 inches, plus 0.3 with a title).
    crop : tuple of int, optional
        (top, left, height, width) in full-size pixels; default :func:`auto_crop` of the
        reference.
    title : str

    Returns
    -------
    Panel
        ``psnr`` and ``labels`` of ``"bicubic"`` and ``"ours"``, and the crop.

    Raises
    ------
    ValueError
        Shapes that differ, or an input not half the reference's size.
    """
    reference = as_rgb(reference, "reference")
    named = _named_images({"bicubic": bicubic, "ours": ours}, "superres_panel")
    _check_shapes(named, reference.shape, "the reference")
    low = as_rgb(low, "low")
    height, width = reference.shape[:2]
    if low.shape[:2] != (height // 2, width // 2) or height % 2 or width % 2:
        raise ValueError(f"low must be half the reference's size {height}x{width}, got {low.shape[:2]}")
    crop = auto_crop(reference) if crop is None else check_crop(crop, height, width)
    exposure = figure_exposure(reference)
    scores, labels = _scored(named, reference, exposure)
    input_name = f"input {low.shape[0]}x{low.shape[1]}"
    shown = {input_name: display(low, "low", exposure),
             **{name: display(image, name, exposure) for name, image in named.items()},
             "reference": display(reference, "reference", exposure)}
    labels_shown = {input_name: "(half size)", **labels, "reference": f"(reference; exposure {exposure:.3g})"}
    written = _comparison(shown, labels_shown, crop, path, title, scales={input_name: 0.5})
    return Panel(written, scores, labels, crop)


def signed_difference(tiled: Any, whole: Any) -> np.ndarray:
    """Per pixel, the channel difference ``tiled - whole`` of largest magnitude, with its sign; (H, W).

    Raises
    ------
    ValueError
        Different shapes or non-finite values.
    """
    tiled, whole = as_rgb(tiled, "tiled"), as_rgb(whole, "whole")
    if tiled.shape != whole.shape:
        raise ValueError(f"tiled {tiled.shape} and whole {whole.shape} differ in shape")
    difference = tiled - whole
    if not np.all(np.isfinite(difference)):
        raise ValueError("the tiled or whole-frame image holds NaN/inf values")
    largest = np.argmax(np.abs(difference), axis=2)
    return np.take_along_axis(difference, largest[:, :, None], axis=2)[:, :, 0]


def pipeline_panel(images: Mapping[str, Any], reference: Any, path: str | Path,
                   difference: tuple[Any, Any] | None = None, title: str = "",
                   reference_label: str = "reference") -> Panel:
    """Figure 8: the §6.4 stages beside the reference and the tiled-minus-whole difference map.

    Parameters
    ----------
    images : mapping
        Stage name -> (H, W[, C]) linear image at the reference's size, in order (e.g.
        :func:`pipeline_stages`: the half-size noisy render and the denoised frame each
        bicubic-upsampled, then denoised + superresolved).
    reference : array_like
        (H, W[, C]) linear reference at the final size.
    path : str or Path
        PNG file (3 inches per panel, 3 high, plus 0.3 with a title).
    difference : (tiled, whole), optional
        The denoiser's output evaluated in tiles and on the whole frame (same shape, any
        size). Shown as the signed :func:`signed_difference` (units of the images: linear
        radiance) on a diverging colour map with symmetric limits and a colour bar.
    title : str
    reference_label : str

    Returns
    -------
    Panel
        ``psnr`` and ``labels`` per stage; ``extras``: ``difference_max`` (largest
        absolute difference) and ``difference_rmse`` (over all channels), when given.

    Raises
    ------
    ValueError
        No stage, shapes that differ, or a non-finite difference.
    """
    reference = as_rgb(reference, "reference")
    named = _named_images(images, "pipeline_panel")
    _check_shapes(named, reference.shape, "the reference")
    if reference_label in named:
        raise ValueError(f"a stage is named like the reference panel, {reference_label!r}")
    exposure = figure_exposure(reference)
    scores, labels = _scored(named, reference, exposure)
    shown = {name: display(image, name, exposure) for name, image in named.items()}
    shown[reference_label] = display(reference, reference_label, exposure)
    labels_shown = {**labels, reference_label: f"(reference; exposure {exposure:.3g})"}
    extras: dict[str, float] = {}
    draw = None
    if difference is not None:
        tiled, whole = difference
        signed = signed_difference(tiled, whole)
        extras["difference_max"] = float(np.max(np.abs(signed)))
        extras["difference_rmse"] = float(np.sqrt(np.mean((as_rgb(tiled, "tiled") - as_rgb(whole, "whole")) ** 2)))

        def draw(figure, axes) -> None:
            limit = extras["difference_max"] or 1e-12  # an all-zero map still needs a range
            picture = axes.imshow(signed, cmap="RdBu_r", vmin=-limit, vmax=limit, interpolation="nearest")
            figure.colorbar(picture, ax=axes, fraction=0.046, pad=0.02)
            axes.set_title("tiled − whole", fontsize=10)
            axes.set_xlabel(f"max |Δ| {extras['difference_max']:.2e}, RMSE {extras['difference_rmse']:.2e}", fontsize=9)
            _bare(axes)

    written = _comparison(shown, labels_shown, None, path, title, extra=draw)
    return Panel(written, scores, labels, None, extras)


# ------------------------------------------------------------------ from models and datasets
def pipeline_stages(noisy: Any, albedo: Any, denoiser, superres, tile: int | None = None
                    ) -> tuple[dict[str, np.ndarray], tuple[np.ndarray, np.ndarray] | None]:
    """The §6.4 stages of one half-size frame, as :mod:`reports.combined` computes them.

    Parameters
    ----------
    noisy, albedo : numpy.ndarray
        (h, w, 3) half-size render and its albedo (linear).
    denoiser, superres : nn.Module
        The scene's denoiser and the superresolution net.
    tile : int, optional
        Also evaluate the denoiser in tiles of this side (a multiple of 32,
        :func:`reconstruction.inference.denoise`) for the difference map.

    Returns
    -------
    images : dict
        ``"noisy, bicubic 2x"``, ``"denoised, bicubic 2x"`` and ``"denoised + SR 2x"``,
        (2h, 2w, 3) each (inputs clipped to [0, 1] before upsampling, as in
        :mod:`reports.combined`).
    difference : (tiled, whole) or None
        The tiled and whole-frame denoiser outputs, (h, w, 3), when ``tile`` is given.
    """
    from reconstruction.baselines import bicubic
    from reconstruction.inference import denoise
    from reconstruction.models import superresolve

    denoised = denoise(denoiser, noisy, albedo)
    was_training = superres.training
    superres.eval()
    final = superresolve(superres, np.clip(denoised, 0.0, 1.0))
    superres.train(was_training)
    images = {"noisy, bicubic 2x": bicubic(np.clip(noisy, 0.0, 1.0)),
              "denoised, bicubic 2x": bicubic(np.clip(denoised, 0.0, 1.0)),
              "denoised + SR 2x": final}
    difference = None if tile is None else (denoise(denoiser, noisy, albedo, tile=tile), denoised)
    return images, difference


def figure_view(dataset, view: str | None = None) -> str:
    """The view the figures show: ``view`` if given (must be accepted), else the first test view in sorted order."""
    if view is not None:
        if view not in dataset.views():
            raise ValueError(f"view {view!r} is not an accepted view of the dataset; test views: {dataset.views('test')}")
        return view
    names = sorted(dataset.views("test"))
    if not names:
        raise ValueError(f"the dataset {dataset.root} has no test view")
    return names[0]



def superres_inputs(reference: np.ndarray, model, downsample: str = "area") -> dict[str, np.ndarray]:
    """The superresolution images of one reference, as :func:`reconstruction.evaluate.superres_images` makes them.

    The reference is clipped to [0, 1] and trimmed to even sides (``"target"``), reduced
    2x by :func:`reconstruction.evaluate.downsample_2x` and clipped (``"low"``), then
    upsampled by :func:`reconstruction.baselines.bicubic` and by
    :func:`reconstruction.models.superresolve` (``"bicubic"``, ``"ours"``).
    """
    from reconstruction.baselines import bicubic
    from reconstruction.evaluate import downsample_2x
    from reconstruction.models import superresolve

    target = np.clip(np.asarray(reference, np.float32), 0.0, 1.0)
    target = target[: target.shape[0] // 2 * 2, : target.shape[1] // 2 * 2]
    low = np.clip(downsample_2x(target, downsample), 0.0, 1.0)
    was_training = model.training
    model.eval()
    ours = superresolve(model, low)
    model.train(was_training)
    return {"target": target, "low": low, "bicubic": bicubic(low), "ours": ours}


def scene_figures(scene_name: str, dataset, models: Mapping[str, Any], superres_model, out_dir: str | Path,
                  view: str | None = None, oidn: bool = True, downsample: str = "area") -> dict[str, Path]:
    """Figures 5 and 7 of one scene, on one test view of its dataset.

    The view is :func:`figure_view` (the first test view in sorted order unless named).
    Denoising panel: the noisy input, each of ``models`` (:func:`reconstruction.evaluate.denoise_view`,
    with the model's own auxiliary buffers), OIDN (:func:`reconstruction.baselines.oidn`
    with albedo and normal) if asked, and the reference. Superresolution panel: the view's
    reference through :func:`superres_inputs`.

    Parameters
    ----------
    scene_name : str
        Used in the titles and file names.
    dataset : reconstruction.data.Dataset
    models : mapping
        Panel name -> denoiser, in order, e.g. ``{"ours": per_scene, "mixed": mixed}``.
    superres_model : nn.Module
    out_dir : str or Path
        Figures go to ``out_dir/figures/``.
    view : str, optional
    oidn : bool
    downsample : {"area", "bicubic"}
        The reduction of the superresolution input (the profile's ``superres_downsample``).

    Returns
    -------
    dict
        ``"<scene>-denoising"`` and ``"<scene>-superres"`` -> PNG path.

    Raises
    ------
    ValueError
        No denoiser given, an unknown view, or a dataset without test views.
    """
    if not models:
        raise ValueError("scene_figures: no denoiser given")
    name = figure_view(dataset, view)
    buffers = dataset.load_view(name)
    images, reference_label = view_images(dataset, buffers, models, oidn)
    figures = Path(out_dir) / "figures"
    split = "test" if name in dataset.views("test") else "non-test"
    denoising = denoising_panel(images, buffers["reference"], figures / f"{scene_name}-denoising.png",
                                title=f"{scene_name}, {name} ({split} view): denoising", reference_label=reference_label)
    sr = superres_inputs(buffers["reference"], superres_model, downsample)
    superres = superres_panel(sr["low"], sr["bicubic"], sr["ours"], sr["target"], figures / f"{scene_name}-superres.png",
                              title=f"{scene_name}, {name} ({split} view): superresolution 2x, {downsample} reduction")
    return {f"{scene_name}-denoising": denoising.path, f"{scene_name}-superres": superres.path}


def view_images(dataset, buffers: Mapping[str, np.ndarray], models: Mapping[str, Any],
                oidn: bool = True) -> tuple[dict[str, np.ndarray], str]:
    """The compared images of one loaded view: the noisy input, each denoiser and OIDN, linear (H, W, 3).

    Parameters
    ----------
    dataset : reconstruction.data.Dataset
        Its manifest's ``spp`` and ``reference_spp`` name the noisy and reference images.
    buffers : mapping
        :meth:`reconstruction.data.Dataset.load_view` of the view.
    models : mapping
        Label -> denoiser, in order (:func:`reconstruction.evaluate.denoise_view`, each with its
        own auxiliary buffers).
    oidn : bool
        Also :func:`reconstruction.baselines.oidn` with albedo and normal, labelled ``"OIDN"``.

    Returns
    -------
    images : dict
        ``"noisy, N spp"`` first, then ``models``' labels, then ``"OIDN"``.
    reference_label : str
        ``"reference, N spp"``.
    """
    from reconstruction.baselines import noisy_input
    from reconstruction.baselines import oidn as oidn_denoise
    from reconstruction.evaluate import denoise_view

    settings = dataset.manifest.get("settings", {})
    spp, reference_spp = settings.get("spp"), settings.get("reference_spp")
    images = {f"noisy, {spp} spp" if spp is not None else "noisy": noisy_input(buffers["noisy"])}
    for label, model in models.items():
        images[label] = denoise_view(model, buffers, tuple(getattr(model, "auxiliary", ("albedo",))))
    if oidn:
        images["OIDN"] = oidn_denoise(buffers["noisy"], buffers["albedo"], buffers["normal"])
    return images, f"reference, {reference_spp} spp" if reference_spp is not None else "reference"


def lit_fraction(reference: Any) -> float:
    """The fraction of a reference's pixels that are lit on display, in [0, 1].

    A pixel is lit when its Rec. 709 luminance times the view's display exposure
    (:func:`reconstruction.metrics.auto_exposure`: the reference's 99th-percentile luminance
    maps to 1) is at least :data:`LIT_FRACTION`. A reference without an exposure (all black
    or not finite) has no lit pixel: 0.
    """
    from reconstruction.metrics import auto_exposure, luminance

    reference = as_rgb(reference, "reference")
    try:
        exposure = auto_exposure(reference)
    except ValueError:
        return 0.0
    return float(np.mean(luminance(reference) * exposure >= LIT_FRACTION))


def strip_view(dataset, split: str | None = "test") -> str:
    """The view of the verdict page's strip: the view of ``split`` whose reference has the most lit pixels.

    **Rule.** Among the accepted views of ``split`` (all accepted views when None), the one with
    the largest :func:`lit_fraction` of its reference (pixels at least :data:`LIT_FRACTION` of
    display white at the metrics' exposure); ties, and a split of only black views, go to the
    first view in sorted name order. It looks at the references alone, never at any method's
    output, and avoids views that are mostly black or empty (a camera facing an unlit wall).

    Raises
    ------
    ValueError
        When the split has no view.
    """
    names = sorted(dataset.views(split))
    if not names:
        raise ValueError(f"the dataset {dataset.root} has no {split or 'accepted'} view")
    scores = [lit_fraction(dataset.load_view(name)["reference"]) for name in names]
    return names[int(np.argmax(scores))]


def write_linear_strip(scene_name: str, dataset, models: Mapping[str, Any], out_dir: str | Path,
                       split: str | None = "test", oidn: bool = True) -> Path:
    """Save the linear images of one scene's verdict strip as EXR, with a manifest, for :mod:`reports.verdict`.

    On the :func:`strip_view` of ``split``: the noisy input, each of ``models`` and OIDN
    (:func:`view_images`) and the reference, each as a float32 EXR (linear radiance, as the
    metrics see it) in ``out_dir/verdict/SCENE/`` (``SCENE`` made file-safe by
    :func:`safe_stem`), and ``strip.json``: the scene, the view, its split, the rule, and per
    image its key, label and file, in strip order (the reference last).

    Parameters
    ----------
    scene_name : str
    dataset : reconstruction.data.Dataset
    models : mapping
        Key -> denoiser in strip order, e.g. ``{"ours": per_scene, "mixed": mixed}``.
    out_dir : str or Path
        The results folder.
    split : str or None
        ``"test"``, or None for every accepted view (a scene no model saw).
    oidn : bool

    Returns
    -------
    Path
        The manifest ``strip.json``.
    """
    from kdtrace.imageio import write_exr

    name = strip_view(dataset, split)
    buffers = dataset.load_view(name)
    images, reference_label = view_images(dataset, buffers, models, oidn)
    keys = ["noisy", *models, *(["oidn"] if oidn else [])]
    labels = {"ours": "ours (per-scene)"}
    folder = Path(out_dir) / STRIP_FOLDER / safe_stem(scene_name)
    entries = []
    for key, (label, image) in zip([*keys, "reference"], [*images.items(), (reference_label, buffers["reference"])],
                                   strict=True):
        write_exr(folder / f"{key}.exr", as_rgb(image, label).astype(np.float32))
        entries.append({"key": key, "label": labels.get(key, label), "file": f"{key}.exr"})
    manifest = {"scene": scene_name, "view": name, "split": split or "all views",
                "rule": f"the {split or 'accepted'} view whose reference has the most pixels at least "
                        f"{LIT_FRACTION:g} of display white at the metrics' exposure",
                "images": entries}
    return atomic_write_bytes(folder / STRIP_MANIFEST, json.dumps(manifest, indent=1).encode())


def safe_stem(name: str) -> str:
    """``name`` as a file name: every run of characters other than letters, digits, ``.``, ``_`` and ``-`` becomes ``_``."""
    return re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip(".") or "_"


def markdown_links(paths: Mapping[str, str | os.PathLike], relative_to: str | Path) -> str:
    """Markdown image links, one per line: ``![name](relative/path.png)``.

    Paths are made relative to ``relative_to`` (the folder of the Markdown file), with
    forward slashes; brackets in names are dropped from the alt text.

    Raises
    ------
    ValueError
        No path given.
    """
    if not paths:
        raise ValueError("markdown_links: no paths given")
    lines = []
    for name, path in paths.items():
        relative = Path(os.path.relpath(Path(os.fspath(path)).resolve(), Path(relative_to).resolve())).as_posix()
        alt = str(name).replace("[", "").replace("]", "")
        lines.append(f"![{alt}]({relative})")
    return "\n".join(lines) + "\n"
