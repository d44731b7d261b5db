"""Images: RGB uint8 arrays [H, W, 3] in memory, PNG on disk (lossless), written atomically."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from facade_pipeline.errors import InputError
from facade_pipeline.io.atomic import atomic_path


def read_image(path: str | Path) -> np.ndarray:
    """Read an 8-bit image as RGB [H, W, 3] uint8 (grey is expanded, alpha dropped)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "an image file", "no file")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(path, "a readable image (PNG, JPEG, TIFF)", "a file OpenCV cannot decode")
    if img.dtype != np.uint8:
        raise InputError(path, "an 8-bit image", f"dtype {img.dtype}")
    if img.ndim == 2:
        img = cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    elif img.shape[2] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2RGB)
    else:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return img


def image_size(path: str | Path) -> tuple[int, int]:
    """(width, height) of an image file, read from its header only."""
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "an image file", "no file")
    try:
        with Image.open(path) as im:
            return im.size
    except (UnidentifiedImageError, OSError) as e:
        raise InputError(path, "a readable image (PNG, JPEG, TIFF)", f"{type(e).__name__}: {e}") from None


def write_image(path: str | Path, rgb: np.ndarray) -> None:
    """Write an RGB (or single-channel) uint8 image atomically; the format follows the suffix."""
    arr = np.asarray(rgb)
    if arr.dtype != np.uint8:
        raise ValueError(f"{path}: expected uint8 pixels, got {arr.dtype}")
    bgr = cv2.cvtColor(arr, cv2.COLOR_RGB2BGR) if arr.ndim == 3 else arr
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), bgr):
            raise OSError(f"{path}: OpenCV could not write the image")


def write_mask(path: str | Path, mask: np.ndarray) -> None:
    """Write a boolean mask as an 8-bit PNG (0 / 255), the form a person can edit by hand."""
    write_image(path, np.where(np.asarray(mask, dtype=bool), 255, 0).astype(np.uint8))


def read_mask(path: str | Path) -> np.ndarray:
    """Read a mask PNG: True where the pixel is at least 128 (any channel layout)."""
    return read_image(path)[..., 0] >= 128


def to_uint8(img: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] -> uint8 with rounding."""
    return np.clip(np.rint(np.asarray(img) * 255.0), 0, 255).astype(np.uint8)
