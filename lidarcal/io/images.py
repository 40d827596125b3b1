"""Image files: decoded by OpenCV, every way a file can fail raised as a :class:`DatasetError`
naming it (missing, a folder, unreadable, empty, cut short, not an image, 16-bit, another
size). The dataset contract's images (``docs/dataset-format.md``) and the photos of
``intrinsics``, ``laser-plane``, ``planes`` and ``import`` are read here."""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from ..laser_colour import laser_response
from .errors import DatasetError


def read_image(path: Path, image_size: tuple[int, int] | None = None, *,
               colour: str = "gray") -> np.ndarray:
    """An 8-bit PNG as a grayscale uint8 array; size checked if given.

    A BGR(A) image becomes gray by OpenCV's luminance weights (``colour="gray"``,
    for the bright board views) or by the brightest channel at each pixel
    (``colour="max"``, for the dark stripe images: a red or green laser keeps its
    full signal instead of 30 % or 59 % of it).
    """
    if colour not in ("gray", "max"):
        raise ValueError(f"colour must be 'gray' or 'max', got {colour!r}")
    img = _decode_8bit(path)
    if img.ndim == 3:
        if colour == "max":
            img = np.ascontiguousarray(img[:, :, :3].max(axis=2))
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY)
    return _checked_size(img, path, image_size)


def _decode_8bit(path: Path) -> np.ndarray:
    """An image as 8 bits per channel (gray or BGR(A)), by :func:`decode_image`: 8-bit as
    stored, 16-bit by :func:`eight_bit_from_16`; DatasetError otherwise."""
    img = decode_image(path, fix="copy it again or drop this position")
    if img.dtype == np.uint16:
        return eight_bit_from_16(img, path)
    if img.dtype != np.uint8:
        raise DatasetError(path, f"expected an 8- or 16-bit image, got {img.dtype}; save it as "
                                 "an 8-bit PNG (gray or BGR)")
    return img


#: A 16-bit image whose values all stay below this holds a 10- or 12-bit sensor's raw values
#: (PNG requires samples scaled to the full 16-bit range): refused, never read near black
MIN_16BIT_TOP = 4096


def eight_bit_from_16(img: np.ndarray, path: Path) -> np.ndarray:
    """A 16-bit image (PNG's full 0-65535 range) as uint8: ``round(v / 257)``, so that
    65535 -> 255 and an 8-bit image stored as 16 bits (``v * 257``) comes back exactly.

    Values that all stay below ``MIN_16BIT_TOP`` (a 10- or 12-bit camera's raw counts
    written unscaled, against the PNG specification) would read as an almost black image
    (at most 16 of 255): DatasetError naming the file instead of a guess of the bit depth.
    """
    top = int(img[..., :3].max()) if img.ndim == 3 else int(img.max())
    if top < MIN_16BIT_TOP:
        raise DatasetError(path, f"16-bit image whose largest value is {top} (below "
                                 f"{MIN_16BIT_TOP}): a 10- or 12-bit camera's raw values not "
                                 "scaled to 16 bits; scale them to 0-65535 (x 16 for 12 bits) "
                                 "or write an 8-bit PNG")
    return ((img.astype(np.uint32) + 128) // 257).astype(np.uint8)


def decode_image(path: str | os.PathLike, flags: int = cv2.IMREAD_UNCHANGED,
                 fix: str = "copy the file again or re-export it") -> np.ndarray:
    """``cv2.imread(path, flags)``, or :class:`DatasetError` naming ``path``, what is wrong
    and ``fix`` (what to do): missing, a folder, unreadable, empty, undecodable (corrupt,
    truncated PNG, not an image) or a truncated JPEG, which ``cv2.imread`` would decode
    without complaint (libjpeg fills the missing rows with gray)."""
    path = Path(path)
    if not path.exists():
        raise DatasetError(path, f"missing image; {fix}")
    if not path.is_file():
        raise DatasetError(path, f"is a folder, not an image file; {fix}")
    try:
        size = path.stat().st_size
        with open(path, "rb") as f:
            head = f.read(8)
            f.seek(max(0, size - 64))
            tail = f.read().rstrip(b"\x00\r\n ")
    except OSError as e:
        raise DatasetError(path, f"cannot be read ({e.strerror or e}); check its permissions or "
                                 f"{fix}") from None
    if size == 0:
        raise DatasetError(path, f"is empty (0 bytes); {fix}")
    # a file cut short (its end marker missing) is refused before libpng prints its own error
    # or libjpeg decodes the missing rows as gray
    for kind, magic, end in (("JPEG", b"\xff\xd8", b"\xff\xd9"),
                             ("PNG", b"\x89PNG\r\n\x1a\n", b"IEND\xaeB`\x82")):
        if head.startswith(magic) and not tail.endswith(end) and not _whole_image(path):
            raise DatasetError(path, f"cannot be decoded: {kind} cut short (its end marker is "
                                     f"missing: a truncated copy or recording); {fix}")
    img = cv2.imread(str(path), flags)
    if img is None:
        raise DatasetError(path, f"cannot be decoded as an image (corrupt, truncated or not an "
                                 f"image file); {fix}")
    return img


def _whole_image(path: Path) -> bool:
    """Whether Pillow decodes the whole image (a JPEG or PNG with data after its end marker,
    e.g. a phone's motion photo, is whole; a truncated one raises)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            im.load()
    except (OSError, SyntaxError, ValueError):
        return False
    return True


def _checked_size(img: np.ndarray, path: Path, image_size: tuple[int, int] | None) -> np.ndarray:
    if image_size is not None and (img.shape[1], img.shape[0]) != tuple(image_size):
        raise DatasetError(Path(path), f"image is {img.shape[1]}x{img.shape[0]}, expected "
                                 f"{image_size[0]}x{image_size[1]} (camera.image_size); give "
                                 "the camera's full, unscaled image")
    return img


def read_stripe_image(path: Path, image_size: tuple[int, int] | None = None,
                      laser_colour: str = "auto") -> np.ndarray:
    """A stripe image as uint8: gray images as they are; colour images by
    :func:`lidarcal.laser_colour.laser_response` (a dark frame by its brightest channel, a
    lights-on photo by the laser colour's excess over the other channels)."""
    if laser_colour == "gray":
        return read_image(path, image_size, colour="max")
    img = _decode_8bit(path)  # decoded once: a gray image is used as it is
    if img.ndim == 2:
        return _checked_size(img, path, image_size)
    return _checked_size(laser_response(img[:, :, :3], laser_colour), path, image_size)
