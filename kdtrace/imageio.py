"""Image files: OpenEXR for linear float data, PNG (sRGB, clamped) for viewing, RGBE planes for
linear data inside a PNG (the verdict page's interactive comparison).

EXR goes through ``mitsuba.Bitmap`` (Mitsuba is a dependency; no OpenEXR or imageio
plugin is needed), PNG through Pillow. Every write is atomic: the file appears under
its name only when complete (temporary file in the same folder, then ``os.replace``).
"""

from __future__ import annotations

import io
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


#: File name endings :func:`read_image` reads as display-encoded (sRGB, 0-1) images.
DISPLAY_SUFFIXES = (".png", ".jpg", ".jpeg")


def read_image(path: str | Path) -> tuple[np.ndarray, bool]:
    """Read an image for comparison as linear float64 RGB, (H, W, 3).

    OpenEXR (linear, through Mitsuba), NumPy ``.npy`` (linear) and PNG/JPEG (sRGB-encoded
    8- or 16-bit, decoded to linear). A grey image is repeated on three channels and an alpha
    channel dropped, as image viewers show them.

    Returns
    -------
    image : ndarray, (H, W, 3), float64
    display_encoded : bool
        True for PNG/JPEG (the file already is the displayed image).

    Raises
    ------
    FileNotFoundError
        When ``path`` does not exist or is a folder.
    ValueError
        Naming the file: an unknown type, an unreadable file, another shape, NaN/inf values.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".exr":
            image = read_exr(path).astype(np.float64)
        elif suffix == ".npy":
            image = np.load(path, allow_pickle=False).astype(np.float64)
        elif suffix in DISPLAY_SUFFIXES:
            from PIL import Image

            with Image.open(path) as opened:
                mode_max = 65535.0 if opened.mode.startswith("I;16") or opened.mode == "I" else 255.0
                image = srgb_decode(np.asarray(opened, dtype=np.float64) / mode_max).astype(np.float64)
        else:
            raise ValueError(f"{path}: unknown image type {suffix!r} (EXR, NPY, PNG or JPEG)")
    except (OSError, RuntimeError, TypeError) as error:
        raise ValueError(f"{path}: cannot be read as an image ({error})") from error
    if image.ndim == 2:
        image = np.repeat(image[:, :, None], 3, axis=2)
    elif image.ndim == 3 and image.shape[2] in (1, 2):
        image = np.repeat(image[:, :, :1], 3, axis=2)
    elif image.ndim == 3 and image.shape[2] == 4:
        image = image[:, :, :3]
    if image.ndim != 3 or image.shape[2] != 3 or 0 in image.shape:
        raise ValueError(f"{path}: expected an image of shape (H, W), (H, W, 3) or (H, W, 4), got {image.shape}")
    bad = int(np.count_nonzero(~np.isfinite(image)))
    if bad:
        raise ValueError(f"{path}: {bad} NaN/inf values")
    return image, suffix in DISPLAY_SUFFIXES


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding of values in [0, 1] (the inverse of :func:`srgb_encode`), float32, same shape."""
    encoded = np.asarray(encoded, np.float32)
    return np.where(encoded <= 0.04045, encoded / 12.92, ((encoded + 0.055) / 1.055) ** 2.4).astype(np.float32)


def write_colour_map(path: str | Path, values: np.ndarray, colormap: str = "magma") -> Path:
    """Write a (H, W) map of values in [0, 1] as an 8-bit PNG through a matplotlib colour map."""
    from matplotlib import colormaps
    from PIL import Image

    rgb = colormaps[colormap](np.clip(np.asarray(values, dtype=np.float64), 0.0, 1.0))[:, :, :3]
    encoded = np.round(rgb * 255.0).astype(np.uint8)
    return atomic_write(path, lambda name: Image.fromarray(encoded).save(name, format="PNG"))


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


def rgbe_encode(image: np.ndarray) -> np.ndarray:
    """Radiance RGBE of a linear (H, W, 3) image as an opaque RGB array of twice its height, uint8 (2H, W, 3).

    Per pixel, with ``v`` its largest channel written ``m · 2**e`` (``m`` in [0.5, 1)): the
    mantissas ``floor(channel · 256 · m / v)`` in rows ``[0, H)``, and the exponent ``e + 128``
    in the red channel of rows ``[H, 2H)`` (green and blue 0). Negative values and NaN become
    0, +inf and values over 2**126 saturate, a pixel whose largest channel is below 2**-127
    is black (exponent 0).
    """
    linear = np.nan_to_num(np.asarray(image, dtype=np.float64), nan=0.0, posinf=2.0**126)
    if linear.ndim != 3 or linear.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) image, got {linear.shape}")
    linear = np.clip(linear, 0.0, 2.0**126)
    largest = linear.max(axis=2)
    mantissa, exponent = np.frexp(largest)
    lit = largest >= 2.0**-127
    scale = np.where(lit, mantissa * 256.0 / np.where(lit, largest, 1.0), 0.0)
    height, width = largest.shape
    planes = np.zeros((2 * height, width, 3), dtype=np.uint8)
    planes[:height] = np.clip(np.floor(linear * scale[:, :, None]), 0, 255).astype(np.uint8)
    planes[height:, :, 0] = np.where(lit, exponent + 128, 0).astype(np.uint8)
    return planes


def rgbe_decode(planes: np.ndarray) -> np.ndarray:
    """The linear (H, W, 3) float32 image of :func:`rgbe_encode`'s planes.

    Each channel is ``(mantissa + 0.5) · 2**(exponent − 136)``, 0 where the exponent is 0.

    The error of each channel is at most 1/256 of the pixel's largest channel (plus the
    saturation and clipping of :func:`rgbe_encode`); the verdict page's script
    (:mod:`reports.verdict_page`) decodes the same way.
    """
    planes = np.asarray(planes)
    height = planes.shape[0] // 2
    exponent = planes[height:, :, 0].astype(np.int32)
    factor = np.where(exponent > 0, np.ldexp(1.0, exponent - 136), 0.0)
    return ((planes[:height].astype(np.float64) + 0.5) * factor[:, :, None]).astype(np.float32)


def png_bytes(array: np.ndarray) -> bytes:
    """An 8-bit (H, W) or (H, W, 3) array as the bytes of a PNG file (Pillow, ``optimize=True``)."""
    from PIL import Image

    buffer = io.BytesIO()
    Image.fromarray(array).save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()
