"""The laser's colour: the single-channel image a stripe is found in (section 1.3 on real
photos).

A dark frame is read by its brightest channel; a lights-on colour photo by the
laser colour's excess over the other two channels, in which lit white squares
vanish while the laser does not; a saturated (white) core is filled from the
stripe's own flanks; an image of the same view without the laser can be
subtracted (stripe minus board).
"""

from __future__ import annotations

import cv2
import numpy as np

#: ``lidar.laser_colour`` values: the laser's colour decides the image the stripe is found in.
LASER_COLOURS = ("auto", "red", "green", "blue", "gray")
_CHANNEL = {"blue": 0, "green": 1, "red": 2}  # OpenCV's BGR order
#: ``auto``: a colour whose excess peaks below this (DN) is not a coloured laser -> "gray".
MIN_COLOUR_EXCESS_DN = 25.0
#: ``auto``: a frame whose median brightest channel is below this (DN) is a dark frame (the
#: V rig's stripe images): the brightest channel keeps the laser's full signal there
DARK_FRAME_DN = 40.0
#: a laser channel at or above this (DN) is saturated (its core is filled, see laser_response)
SATURATED_DN = 250


def _colour_excess(img: np.ndarray, colour: str) -> np.ndarray:
    """``L - (O1 + O2) / 2`` (float32) for the laser channel ``L`` and the two others."""
    f = img[..., :3].astype(np.float32)
    k = _CHANNEL[colour]
    others = [c for c in range(3) if c != k]
    return f[..., k] - 0.5 * (f[..., others[0]] + f[..., others[1]])


def detect_laser_colour(image: np.ndarray, reference: np.ndarray | None = None) -> str:
    """The laser's colour for ``lidar.laser_colour: auto``: "red", "green", "blue" or "gray".

    A gray image is "gray". Otherwise each channel's excess over the other two
    (:func:`_colour_excess`; of the difference to ``reference``, a lights-on image
    without the laser, when given) is taken at its 99.95th percentile; the strongest
    wins if it reaches ``MIN_COLOUR_EXCESS_DN``, else the laser is "gray" (white, or
    a NIR laser that every channel sees alike).
    """
    img = np.asarray(image)
    if img.ndim == 2 or img.shape[2] == 1:
        return "gray"
    f = img[..., :3].astype(np.float32)
    if reference is not None and np.shape(reference)[:2] == img.shape[:2] \
            and np.ndim(reference) == 3:
        f = f - np.asarray(reference)[..., :3].astype(np.float32)
    sub = f[::2, ::2]
    score = {c: float(np.percentile(_colour_excess(sub, c), 99.95)) for c in _CHANNEL}
    best = max(score, key=score.get)
    return best if score[best] >= MIN_COLOUR_EXCESS_DN else "gray"


def laser_response(image: np.ndarray, colour: str = "auto",
                   reference: np.ndarray | None = None, core_max_px: int = 15) -> np.ndarray:
    """The single-channel uint8 image the stripe is found in (section 1.3, real photos).

    ``colour`` (``lidar.laser_colour``): "gray" takes the brightest channel (a dark
    frame, or a NIR laser); "red", "green", "blue" the colour excess ``L - (O1 + O2) / 2``,
    in which lit white squares are ~0 while the laser is not; "auto" decides by
    :func:`detect_laser_colour`, except on a dark frame (median below ``DARK_FRAME_DN``),
    which is read by its brightest channel. A saturated laser core turns white (all channels
    clip), which the excess would hollow out: where the laser channel is saturated the
    response is the largest excess within a few pixels (the stripe's own flanks), so
    the core is a flat top, symmetric about the centre. ``reference``: a lights-on
    image of the same view without the laser (``board.png``); its response is
    subtracted (stripe minus board) when ``image`` is itself lit (its median at least
    half the reference's), removing what the board shows without the laser.
    ``core_max_px``: the widest saturated core filled (:data:`CORE_MAX_PX`; a large photo's
    core is wider: :mod:`lidarcal.laserplane` scales it with the board's squares), a
    clipped area wider than that every way (:func:`clipped_areas`) is not filled.
    """
    img = np.asarray(image)
    if colour not in LASER_COLOURS:
        raise ValueError(f"laser colour must be one of {', '.join(LASER_COLOURS)}, got {colour!r}")
    if colour == "auto":
        dark = img.ndim == 3 and reference is None and \
            float(np.median(img[::4, ::4, :3].max(axis=2))) < DARK_FRAME_DN
        colour = "gray" if dark else detect_laser_colour(img, reference)
    if img.ndim == 2 or colour == "gray":
        resp = img.astype(np.float32) if img.ndim == 2 else \
            img[..., :3].max(axis=2).astype(np.float32)
        ref = None if reference is None else laser_response(reference, "gray")
    else:
        resp = _colour_excess(img, colour)
        sat = img[..., _CHANNEL[colour]] >= SATURATED_DN
        if sat.any():
            r = int(core_max_px) // 2  # fills cores up to core_max_px wide; far from a
            # stripe saturated squares stay 0
            se = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * r + 1,) * 2)
            filled = cv2.dilate(resp, se)
            # a clipped white square (wider than a core every way) is not filled: the laser
            # cannot be seen there, and the fill would copy the stripe on the next black
            # square into it, on one side only
            resp = np.where(sat & ~clipped_areas(img, colour, core_max_px),
                            np.maximum(resp, filled), resp)
        ref = None
        if reference is not None and np.ndim(reference) == 3:
            ref = np.clip(_colour_excess(np.asarray(reference), colour), 0, 255)
    if ref is not None and ref.shape == resp.shape:
        lit = np.median(resp[::4, ::4]) >= 0.5 * max(float(np.median(ref[::4, ::4])), 1.0)
        if lit:
            resp = resp - ref
    return np.clip(np.rint(resp), 0, 255).astype(np.uint8)


#: a clipped area of the laser's channel wider than this (px, every way) is not a stripe's core
CORE_MAX_PX = 15


def clipped_areas(image: np.ndarray, colour: str, core_max_px: int = CORE_MAX_PX
                  ) -> np.ndarray:
    """Where the laser's channel clips over an area wider than a stripe's core (bool, H x W;
    ``core_max_px`` every way): overexposed white squares, lamps. The laser cannot be seen there (its channel is full
    already): the core fill of :func:`laser_response` leaves them out and the stripe search
    of :mod:`lidarcal.laserplane` keeps its profiles off them."""
    sat = (np.asarray(image)[..., _CHANNEL[colour]] >= SATURATED_DN).view(np.uint8)
    se = cv2.getStructuringElement(cv2.MORPH_RECT, (int(core_max_px), int(core_max_px)))
    return cv2.morphologyEx(sat, cv2.MORPH_OPEN, se).view(bool)


def _line_kernel(angle: float, length_px: float) -> np.ndarray:
    """A normalised line of ``length_px`` at ``angle`` (rad, image x towards y), odd square."""
    n = int(2 * np.ceil(length_px / 2) + 1)
    k = np.zeros((n, n), np.float32)
    t = np.linspace(-length_px / 2, length_px / 2, 4 * n)
    c = n // 2
    k[np.round(c + t * np.sin(angle)).astype(int), np.round(c + t * np.cos(angle)).astype(int)] = 1
    return k / k.sum()


#: directions (deg) searched for the stripe by :func:`along_stripe`, and a board edge
#: direction's neighbourhood left out of the search (its colour fringes lie along it)
ALONG_STEP_DEG = 3.0
EDGE_GUARD_DEG = 6.0
#: the direction search runs on the mask's box reduced to at most this many px
ALONG_SEARCH_PX = 800


def along_stripe(response: np.ndarray, mask: np.ndarray, length_px: float,
                 avoid_deg: tuple[float, ...] = (), smooth_px: float | None = None,
                 direction_deg: float | None = None) -> tuple[np.ndarray, float]:
    """The response averaged along the stripe's direction, and that direction (deg).

    A line laser on a flat board is a straight line in the image (a curve under lens
    distortion, straight over a short length); the colour fringes that demosaicing, JPEG's
    4:2:0 chroma and lens colour put along the board's square edges, and JPEG's chroma
    block noise, are not. The direction is the one (``ALONG_STEP_DEG`` steps, refined to
    a tenth, away from the ``avoid_deg`` directions by ``EDGE_GUARD_DEG``) whose average
    over a line of ``length_px`` has the highest 99.9th percentile inside ``mask``
    (searched on the mask's box reduced to ``ALONG_SEARCH_PX``); the response is then
    averaged over a line of ``smooth_px`` (default ``length_px``) in that direction
    (symmetric: a straight stripe's centre does not move) at full resolution within the
    mask's box (zero outside). A directional matched filter, as
    line detectors by oriented filters (Freeman & Adelson 1991, steerable filters).
    ``direction_deg`` given: that direction, not searched (the stripe centres' own line,
    :func:`centres_direction_deg`).
    """
    ys, xs = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    out = np.zeros(response.shape, np.uint8)
    if ys.size == 0:
        return out, float("nan")
    pad = int(np.ceil(length_px / 2)) + 2
    y0, y1 = max(ys[0] - pad, 0), min(ys[-1] + 1 + pad, response.shape[0])
    x0, x1 = max(xs[0] - pad, 0), min(xs[-1] + 1 + pad, response.shape[1])
    crop = response[y0:y1, x0:x1].astype(np.float32)
    s = min(1.0, ALONG_SEARCH_PX / max(crop.shape))
    small = cv2.resize(crop, None, fx=s, fy=s, interpolation=cv2.INTER_AREA) if s < 1 else crop
    msmall = cv2.resize(mask[y0:y1, x0:x1].astype(np.uint8), (small.shape[1], small.shape[0]),
                        interpolation=cv2.INTER_NEAREST).astype(bool)
    if not msmall.any():
        return out, float("nan")
    best = (float(direction_deg) % 180 if direction_deg is not None
            else _search_direction(small, msmall, s * length_px, avoid_deg))
    f = cv2.filter2D(crop, -1, _line_kernel(np.radians(best), smooth_px or length_px))
    out[y0:y1, x0:x1] = np.clip(np.rint(f), 0, 255).astype(np.uint8)
    return out, best


def _search_direction(small: np.ndarray, msmall: np.ndarray, length_px: float,
                      avoid_deg: tuple[float, ...]) -> float:
    """:func:`along_stripe`'s direction search on the reduced crop: the direction (deg) whose
    line filter of ``length_px`` gives the brightest 0.1 % inside ``msmall``, coarse steps of
    ``ALONG_STEP_DEG`` away from ``avoid_deg``, then a tenth of a step."""
    def score(deg: float) -> float:
        f = cv2.filter2D(small, -1, _line_kernel(np.radians(deg), max(3.0, length_px)))
        return float(np.percentile(f[msmall], 99.9))

    def allowed(deg: float) -> bool:
        return all(abs((deg - a + 90) % 180 - 90) > EDGE_GUARD_DEG for a in avoid_deg)

    cands = [a for a in np.arange(0, 180, ALONG_STEP_DEG) if allowed(a)] or \
        list(np.arange(0, 180, ALONG_STEP_DEG))
    best = max(cands, key=score)
    fine = [best + d for d in np.arange(-ALONG_STEP_DEG / 2, ALONG_STEP_DEG / 2 + 1e-9,
                                        ALONG_STEP_DEG / 10)]
    return float(max(fine, key=score)) % 180


def centres_direction_deg(centres_px: np.ndarray) -> float | None:
    """The direction (deg, image x towards y, 0..180) of the principal axis of stripe centres
    (N, 2) px; None with fewer than 5. Over the whole board the centres fix the stripe's
    direction far better than :func:`along_stripe`'s search, whose score (the brightest
    0.1 % of the averaged response) a speckled stripe seen in short pieces (overexposed white
    squares between them) can turn by several degrees."""
    c = np.asarray(centres_px, float).reshape(-1, 2)
    if len(c) < 5:
        return None
    _, _, vt = np.linalg.svd(c - c.mean(0), full_matrices=False)
    return float(np.degrees(np.arctan2(vt[0, 1], vt[0, 0]))) % 180
