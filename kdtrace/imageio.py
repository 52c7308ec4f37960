"""Image files: OpenEXR for linear float data, PNG (sRGB, clamped) for viewing.

EXR goes through ``mitsuba.Bitmap`` (Mitsuba is a dependency; no OpenEXR or imageio
plugin is needed), PNG through Pillow. Every write is atomic: the file appears under
its name only when complete (temporary file in the same folder, then ``os.replace``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from kdtrace.cache import atomic_write


def _float_image(image: np.ndarray) -> np.ndarray:
    image = np.ascontiguousarray(image, dtype=np.float32)
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3)):
        raise ValueError(f"image must have shape (H, W), (H, W, 1) or (H, W, 3), got {image.shape}")
    return image


def write_exr(path: str | Path, image: np.ndarray) -> Path:
    """Write linear float data (H, W) or (H, W, 3) as a float32 OpenEXR file.

    Returns
    -------
    Path
        The written file.
    """
    import mitsuba

    image = _float_image(image)
    return atomic_write(path, lambda name: mitsuba.Bitmap(image).write(name))


def read_exr(path: str | Path) -> np.ndarray:
    """Read an OpenEXR file as float32 (H, W) or (H, W, C)."""
    import mitsuba

    return np.array(mitsuba.Bitmap(str(path)), dtype=np.float32)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """sRGB transfer function of linear values clamped to [0, 1] (NaN -> 0)."""
    linear = np.clip(np.nan_to_num(np.asarray(linear, dtype=np.float64), nan=0.0), 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1.0 / 2.4) - 0.055)


def write_png(path: str | Path, image: np.ndarray, exposure: float = 1.0) -> Path:
    """Write linear data as an 8-bit sRGB PNG (times ``exposure``, clamped to [0, 1])."""
    from PIL import Image

    image = _float_image(image)
    if image.ndim == 3 and image.shape[2] == 1:
        image = image[:, :, 0]
    encoded = np.round(srgb_encode(image * exposure) * 255.0).astype(np.uint8)
    return atomic_write(path, lambda name: Image.fromarray(encoded).save(name, format="PNG"))


def write_render(result, directory: str | Path, stem: str = "render") -> dict[str, Path]:
    """Write a :class:`~kdtrace.render.RenderResult`: EXR of every buffer plus a PNG preview.

    Returns
    -------
    dict
        Buffer name (``rgb``, ``variance``, ``albedo``, ``normal``, ``depth``, ``png``) -> file.
    """
    directory = Path(directory)
    written = {"png": write_png(directory / f"{stem}.png", result.rgb)}
    for name in ("rgb", "variance", "albedo", "normal", "depth"):
        buffer = getattr(result, name)
        if buffer is not None:
            written[name] = write_exr(directory / f"{stem}-{name}.exr", buffer)
    return written
