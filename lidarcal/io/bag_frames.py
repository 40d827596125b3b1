"""Camera frames of a bag: decoding (``image_from_msg``) and, when one camera topic holds
both the lit board and the dark stripe frames, telling them apart.

Many rigs record a single camera stream (``/camera/image_raw`` or its ``/compressed``
copy): the lights are on for a while at a stop (the V-board image), then off (the laser
stripes). Each frame taken while the turntable holds still is classified by its own
brightness, the median gray level of the frame (a lit board fills the view with
mid-grays, a stripe frame is black but for thin lines). The lit/dark threshold comes
from the data: Otsu's method (N. Otsu, "A threshold selection method from gray-level
histograms", IEEE SMC 1979) on the per-frame medians, accepted only when the light at
least doubles the level: the dimmest lit median above twice (the brightest dark one plus
one gray level), a ratio independent of exposure that no flicker of the dark level by a
gray level or two passes, so a recording with dark frames only has no lit frame. Otsu's
separability ``eta = sigma_B^2 / sigma_T^2`` is reported with the split (it is lower when
the lit frames come at two light levels, which is fine).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .dataset import DatasetError

COMPRESSED = "sensor_msgs/msg/CompressedImage"
# cv_bridge's conversions of raw sensor layouts to BGR (OpenCV names a Bayer pattern by its
# second row's first two pixels: ROS bayer_rggb8 is OpenCV's BayerBG)
_BAYER = {"bayer_rggb8": cv2.COLOR_BayerBG2BGR, "bayer_bggr8": cv2.COLOR_BayerRG2BGR,
          "bayer_gbrg8": cv2.COLOR_BayerGR2BGR, "bayer_grbg8": cv2.COLOR_BayerGB2BGR}
_YUV422 = {"yuv422": cv2.COLOR_YUV2BGR_UYVY, "uyvy": cv2.COLOR_YUV2BGR_UYVY,
           "yuv422_yuy2": cv2.COLOR_YUV2BGR_YUY2, "yuyv": cv2.COLOR_YUV2BGR_YUY2}
MIN_LIT_RATIO = 2.0  # the lights at least double the frame median


def frame_brightness(img: np.ndarray) -> float:
    """The median gray level of a frame (every 4th pixel; colour frames by their gray value)."""
    g = img if img.ndim == 2 else cv2.cvtColor(img[:, :, :3], cv2.COLOR_BGR2GRAY)
    return float(np.median(g[::4, ::4]))


@dataclass(frozen=True)
class LitSplit:
    """The lit/dark split of the still frames' medians."""

    threshold: float  # a frame is lit when its median is above this
    separability: float  # Otsu's eta in 0..1
    dark_max: float
    lit_min: float
    lo: float  # brightness range seen
    hi: float

    @property
    def has_lit(self) -> bool:
        return np.isfinite(self.threshold)


def otsu_split(x: np.ndarray) -> tuple[float, float]:
    """Otsu's threshold (Otsu 1979) on the values ``x``: the cut between two sorted values
    that maximises the between-class variance ``w0 w1 (mu1 - mu0)^2``. Returns the largest
    value of the lower class and ``eta = sigma_B^2 / sigma_T^2``."""
    v = np.sort(np.asarray(x, dtype=float))
    n = v.size
    cut = np.flatnonzero(np.diff(v) > 0)  # class 0 = v[:i + 1]
    if cut.size == 0:
        return float("inf"), 0.0
    c = np.cumsum(v)
    k = cut + 1.0
    mu0, mu1 = c[cut] / k, (c[-1] - c[cut]) / (n - k)
    sigma_b = (k / n) * (1 - k / n) * (mu1 - mu0) ** 2
    best = int(np.argmax(sigma_b))
    return float(v[cut[best]]), float(sigma_b[best] / v.var())


def split_lit_dark(medians: np.ndarray) -> LitSplit:
    """Lit and dark frames from their medians: Otsu's threshold (Otsu 1979) on
    ``log(1 + median)`` (the light multiplies the level, so two lit levels stay one class),
    accepted when the dimmest lit median exceeds ``MIN_LIT_RATIO * (brightest dark median
    + 1)``; otherwise ``threshold = inf`` (every frame dark). A frame is lit when its
    median is above ``threshold`` (the brightest dark median)."""
    m = np.asarray(medians, dtype=float)
    lo, hi = (float(m.min()), float(m.max())) if m.size else (float("nan"), float("nan"))
    th_log, eta = otsu_split(np.log1p(m)) if m.size >= 2 else (float("inf"), 0.0)
    if not np.isfinite(th_log):
        return LitSplit(float("inf"), 0.0, hi, float("inf"), lo, hi)
    lit = np.log1p(m) > th_log
    split = LitSplit(float(m[~lit].max()), eta, float(m[~lit].max()), float(m[lit].min()), lo, hi)
    if split.lit_min <= MIN_LIT_RATIO * (split.dark_max + 1.0):
        return LitSplit(float("inf"), eta, hi, float("inf"), lo, hi)
    return split


def image_from_msg(msg, msgtype: str, where: str) -> np.ndarray:
    """An 8-bit gray (H, W) or BGR (H, W, 3) image from an Image or CompressedImage message
    (Bayer and YUV 4:2:2 frames converted to BGR with cv_bridge's OpenCV conversions)."""
    if msgtype == COMPRESSED:
        img = cv2.imdecode(np.frombuffer(bytes(msg.data), np.uint8), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise DatasetError(where, f"a CompressedImage ({msg.format!r}) cannot be decoded; "
                                      "png and jpeg are supported")
    else:
        enc = msg.encoding.lower()
        h, w, step = int(msg.height), int(msg.width), int(msg.step)
        buf = np.frombuffer(bytes(msg.data), np.uint8)
        chans = {"mono8": 1, "8uc1": 1, "mono16": 2, "16uc1": 2, "bgr8": 3, "rgb8": 3,
                 "8uc3": 3, "bgra8": 4, "rgba8": 4, **dict.fromkeys(_BAYER, 1),
                 **dict.fromkeys(_YUV422, 2)}
        if enc not in chans:
            raise DatasetError(where, f"image encoding {msg.encoding!r} is not supported; record "
                                      "mono8, mono16, bgr8, rgb8, bayer_*8 or yuv422 (or "
                                      "png/jpeg compressed)")
        if buf.size < h * step or step < w * chans[enc]:
            raise DatasetError(where, f"image data of {buf.size} bytes does not fit "
                                      f"{w}x{h} {enc} with step {step}")
        rows = buf[: h * step].reshape(h, step)[:, : w * chans[enc]]
        if enc in _BAYER:  # demosaiced as cv_bridge does
            img = cv2.cvtColor(np.ascontiguousarray(rows), _BAYER[enc])
        elif enc in _YUV422:
            img = cv2.cvtColor(np.ascontiguousarray(rows).reshape(h, w, 2), _YUV422[enc])
        elif chans[enc] == 2:
            img = np.ascontiguousarray(rows).view(">u2" if msg.is_bigendian else "<u2")
        elif chans[enc] == 1:
            img = rows
        else:
            img = rows.reshape(h, w, chans[enc])
            if enc.startswith("rgb"):
                img = img[:, :, [2, 1, 0] + ([3] if chans[enc] == 4 else [])]
    if img.dtype == np.uint16:
        img = np.clip((img.astype(np.uint32) + 128) >> 8, 0, 255).astype(np.uint8)
    if img.dtype != np.uint8:
        raise DatasetError(where, f"expected 8- or 16-bit images, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    return np.ascontiguousarray(img)
