"""LiDAR scans by ray casting, with a beam-footprint (mixed pixel) return model.

Footprint and return model
--------------------------
Each beam is a Gaussian beam: its 1/e^2 footprint radius at range ``r`` is
``beam_exit_mm / 2 + r * beam_divergence_mrad / 2000``. The footprint is
sampled by sub-rays on concentric rings (``footprint_rings``; 3 rings = 37
sub-rays) reaching out to the 1/e^2 radius, each carrying the Gaussian
energy ``exp(-2 s^2)`` of its position ``s`` (in units of that radius),
normalised to sum to 1. A sub-ray returns the energy
``weight * reflectivity(material) * cos(incidence)``; surfaces beyond
``range_max`` return nothing.

The echo is energy-weighted over the surfaces in the footprint (SICK-like
single echo): a surface with a share below ``1 - mixed_dominant`` of the
returned energy is ignored; the reported range is the energy-weighted mean
range of the remaining surfaces. So a beam mostly (>= ``mixed_dominant``) on
one surface reports that surface's range; a beam split between a board (or
the disc) and the wall behind it reports a "mixed pixel" floating between
them, in proportion to their energies. No return (0) when the total returned
energy is below ``detect_energy`` or the range is outside
``[range_min, range_max]``. Then Gaussian range noise (``range_noise_mm``)
(plus ``range_noise_rel`` times the range) is added; in the harsh preset ``spurious_rate`` of the beams get a uniform
random range and ``drop_rate`` of them return nothing. Ranges are rounded to
0.1 mm as written.

Second model, ``footprint_model = "first-echo"`` (a pulsed first-return
scanner): the spot is uniform (top-hat, equal sub-ray weights) out to the same
radius, and the echo is the *nearest* surface that returns at least
``echo_threshold`` of the footprint's energy, at its own energy-weighted range:
never a mixed range. The rim is then found where ``echo_threshold`` of the
returned energy comes from the disc, outside the half-energy point, so the
disc looks larger by a fraction of the spot (what an edge model must absorb).

Ranging errors (all off by default, see :class:`~lidarcal.synthetic.config.RigConfig`):
``dark_extra_mm`` is added to the range of every sub-ray that hits a black
square (a time-of-flight sensor reads weak returns late), so a beam wholly on
a black square reads exactly that much farther and one straddling a square
edge in proportion to the energy on black (:func:`dark_range_bias`);
``range_offset_mm`` is added to every valid range before the noise (a zero
offset); ``range_quantum_mm`` rounds the noisy ranges to multiples of the
quantum (e.g. 1 mm: a Hokuyo UTM-30LX reports integer mm) before the range
window is applied (:func:`apply_ranging_errors`); ``incidence_extra_mm`` lengthens
each sub-ray's range by ``incidence_extra_mm * (1 / cos(incidence) - 1)`` (a pulse
stretched on an oblique surface triggers late; :func:`incidence_range_bias`) and
``range_scale_error`` multiplies every valid range by ``1 + range_scale_error`` (a
time-base error) with the offset.

Speed: each beam is first probed with 7 sub-rays (centre + 6 on the outer
ring); only beams whose probes do not all hit the same surface are traced
with the full footprint. A surface boundary that cuts only a sliver of the
footprint between two probes is missed; such slivers carry less energy than
the ``1 - mixed_dominant`` share that would matter.

Consequence at a rim (paper preset: footprint 3.75 mm at 1.5 m, beams 2.2 mm
apart, sweep steps 1.3 mm): a beam reports the disc range only when about a
footprint-sigma (~1 mm) of it lies inside the rim; the outermost disc-range
returns lie on average ~1.1 mm inside the true rim (bundled data), the next
beam out is a mixed pixel (off the disc plane) or a wall return.
"""

from __future__ import annotations

import numpy as np

from .config import RigConfig
from .scene import BLACK, DISC, POST, WALL, WHITE, materials, surface_normals, trace


def footprint_pattern(rings: int, profile: str = "gaussian") -> tuple[np.ndarray, np.ndarray]:
    """Sub-ray offsets in the unit disc (M, 2) and energy weights (M,) summing to 1.

    ``profile``: ``"gaussian"`` (weight ``exp(-2 s^2)``, the 1/e^2 radius at s = 1) or
    ``"uniform"`` (top-hat: equal weights; ring i holds 6 i sub-rays, so equal area each).
    """
    pts = [np.zeros((1, 2))]
    for i in range(1, rings + 1):
        a = 2 * np.pi * (np.arange(6 * i) + 0.5 * (i % 2)) / (6 * i)
        pts.append(i / rings * np.column_stack([np.cos(a), np.sin(a)]))
    s = np.vstack(pts)
    if profile == "uniform":
        return s, np.full(len(s), 1.0 / len(s))
    if profile != "gaussian":
        raise ValueError(f"unknown footprint profile {profile!r}; expected 'gaussian' or 'uniform'")
    w = np.exp(-2 * (s**2).sum(1))
    return s, w / w.sum()


def reflectivity_table(rig: RigConfig) -> np.ndarray:
    board, wall, post, disc = rig.lidar_reflectivity
    t = np.zeros(6)
    t[WHITE] = t[BLACK] = board
    t[WALL], t[POST], t[DISC] = wall, post, disc
    return t


def beam_angles_deg(rig: RigConfig) -> np.ndarray:
    """Beam ``k`` at ``angle_min + k * step`` (the dataset contract)."""
    n = round((rig.lidar_angle_max_deg - rig.lidar_angle_min_deg) / rig.lidar_angle_step_deg) + 1
    return rig.lidar_angle_min_deg + np.arange(n) * rig.lidar_angle_step_deg


def _energy(surfaces: list, t: np.ndarray, idx: np.ndarray, orig: np.ndarray, dirs: np.ndarray,
            w: np.ndarray, refl: np.ndarray, rig: RigConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returned energy per sub-ray: weight * reflectivity * cos(incidence); nothing beyond range_max."""
    hit = (idx >= 0) & (t <= rig.lidar_range_max_mm)
    t = np.where(hit, t, 0.0)
    idx = np.where(hit, idx, -1)
    pts = orig + dirs * t[:, None]
    mat = materials(surfaces, pts, idx)
    nrm = surface_normals(surfaces, pts, idx)
    cos_inc = np.abs(np.einsum("ij,ij->i", nrm, dirs))
    if rig.dark_extra_mm:
        t = t + dark_range_bias(mat, rig)
    if rig.incidence_extra_mm:
        t = t + np.where(idx >= 0, incidence_range_bias(cos_inc, rig), 0.0)
    return t, idx, w * refl[mat] * cos_inc


def incidence_range_bias(cos_inc: np.ndarray, rig: RigConfig) -> np.ndarray:
    """Extra range (mm) of sub-rays by incidence: ``incidence_extra_mm * (1 / cos - 1)``
    (0 at normal incidence; the cosine floored at 0.1, i.e. 84 deg)."""
    return float(rig.incidence_extra_mm) * (1.0 / np.maximum(np.asarray(cos_inc, float), 0.1) - 1.0)


def dark_range_bias(mat: np.ndarray, rig: RigConfig) -> np.ndarray:
    """Extra range (mm) of sub-rays by material: ``dark_extra_mm`` on black squares, else 0."""
    return np.where(np.asarray(mat) == BLACK, float(rig.dark_extra_mm), 0.0)


def apply_ranging_errors(ranges_mm: np.ndarray, rig: RigConfig, stage: str) -> np.ndarray:
    """The LiDAR's systematic ranging errors on ranges (0 = no return), by stage.

    ``stage="offset"`` (before the noise): every valid range reads
    ``range_offset_mm`` too far. ``stage="quantise"`` (after the noise, spurious
    returns and dropouts): ranges rounded to multiples of ``range_quantum_mm``.
    A zero setting leaves the array untouched (the default rigs' bytes).
    """
    r = np.asarray(ranges_mm, dtype=float)
    if stage == "offset":
        if rig.range_scale_error:
            r = r * (1.0 + rig.range_scale_error)
        return r + (r > 0) * rig.range_offset_mm if rig.range_offset_mm else r
    if stage == "quantise":
        q = rig.range_quantum_mm
        return np.round(r / q) * q if q > 0 else r
    raise ValueError(f"stage must be 'offset' or 'quantise', got {stage!r}")


def beam_materials(surfaces: list, R: np.ndarray, T: np.ndarray, rig: RigConfig,
                   angles_deg: np.ndarray | None = None) -> np.ndarray:
    """Material code (scene :data:`~lidarcal.synthetic.scene.MATERIALS`) hit by each beam's centre ray.

    Shape (P, B) for poses ``R`` (P, 3, 3), ``T`` (P, 3); tells which square a
    beam hits (``BLACK`` returns carry ``dark_extra_mm``), ``NOTHING`` past range_max.
    """
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    T = np.asarray(T, dtype=float).reshape(-1, 3)
    ang = np.radians(beam_angles_deg(rig) if angles_deg is None else np.asarray(angles_deg, float))
    d = np.column_stack([np.cos(ang), np.sin(ang), np.zeros(len(ang))])
    dirs = np.einsum("pij,bj->pbi", R, d).reshape(-1, 3)
    orig = np.repeat(T, len(ang), axis=0)
    t, idx = trace(surfaces, dirs, origins=orig)
    idx = np.where(t <= rig.lidar_range_max_mm, idx, -1)
    pts = orig + dirs * np.where(np.isfinite(t), t, 0.0)[:, None]
    return materials(surfaces, pts, idx).reshape(len(R), len(ang))


def _cast(surfaces: list, R: np.ndarray, T: np.ndarray, o_l: np.ndarray, d_l: np.ndarray, w: np.ndarray,
          refl: np.ndarray, rig: RigConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-rays (B, M) of every beam at poses (n): range, surface index, energy, each (n, B, M)."""
    n, (B, M) = len(R), o_l.shape[:2]
    dirs = np.einsum("pij,bmj->pbmi", R, d_l).reshape(-1, 3)
    orig = (np.einsum("pij,bmj->pbmi", R, o_l) + T[:, None, None, :]).reshape(-1, 3)
    t, idx = trace(surfaces, dirs, origins=orig)
    t, idx, e = _energy(surfaces, t, idx, orig, dirs, np.tile(w, n * B), refl, rig)
    return t.reshape(n, B, M), idx.reshape(n, B, M), e.reshape(n, B, M)


def _echo(t: np.ndarray, idx: np.ndarray, e: np.ndarray, n_surf: int, rig: RigConfig) -> np.ndarray:
    """Energy-weighted echo of beams (N, M sub-rays); see the module docstring. 0 = no return."""
    E = np.zeros((n_surf,) + t.shape[:-1])
    Rs = np.zeros_like(E)
    for k in range(n_surf):
        ek = np.where(idx == k, e, 0.0)
        E[k] = ek.sum(-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            Rs[k] = np.nan_to_num((ek * t).sum(-1) / E[k])
    tot = E.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = E / tot
        wk = np.where(share >= 1 - rig.mixed_dominant, share, 0.0)
        rng_mm = (wk * Rs).sum(0) / wk.sum(0)
    return np.where(tot >= rig.detect_energy, np.nan_to_num(rng_mm), 0.0)


def _first_echo(t: np.ndarray, idx: np.ndarray, e: np.ndarray, n_surf: int,
                rig: RigConfig) -> np.ndarray:
    """First-echo return of beams (N, M sub-rays): the nearest surface with >= ``echo_threshold``
    of the returned energy, at its energy-weighted range (never mixed). 0 = no return."""
    E = np.zeros((n_surf,) + t.shape[:-1])
    Rs = np.full_like(E, np.inf)
    for k in range(n_surf):
        ek = np.where(idx == k, e, 0.0)
        E[k] = ek.sum(-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            Rs[k] = np.where(E[k] > 0, (ek * t).sum(-1) / E[k], np.inf)
    tot = E.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        strong = E / tot >= rig.echo_threshold
    rng_mm = np.where(strong, Rs, np.inf).min(0)
    return np.where((tot >= rig.detect_energy) & np.isfinite(rng_mm), rng_mm, 0.0)


def _echo_function(rig: RigConfig):
    """The echo model and spot profile of ``rig.footprint_model``."""
    if rig.footprint_model == "gaussian":
        return _echo, "gaussian"
    if rig.footprint_model == "first-echo":
        return _first_echo, "uniform"
    raise ValueError(f"unknown footprint_model {rig.footprint_model!r}; expected 'gaussian' or 'first-echo'")


def simulate_scans(surfaces: list, R: np.ndarray, T: np.ndarray, rig: RigConfig,
                   rng: np.random.Generator, angles_deg: np.ndarray | None = None) -> np.ndarray:
    """Ranges (P, B) in mm (0 = no return) of the LiDAR at poses ``R`` (P, 3, 3), ``T`` (P, 3).

    See the module docstring for the footprint and return model.
    """
    R = np.asarray(R, dtype=float).reshape(-1, 3, 3)
    T = np.asarray(T, dtype=float).reshape(-1, 3)
    ang = np.radians(beam_angles_deg(rig) if angles_deg is None else np.asarray(angles_deg, float))
    B, P = len(ang), len(R)
    echo, profile = _echo_function(rig)
    s, wgt = footprint_pattern(rig.footprint_rings, profile)
    M = len(s)
    c, sn = np.cos(ang), np.sin(ang)
    d = np.column_stack([c, sn, np.zeros(B)])
    e1 = np.column_stack([-sn, c, np.zeros(B)])
    e2 = np.tile([0.0, 0.0, 1.0], (B, 1))
    lat = s[None, :, 0, None] * e1[:, None, :] + s[None, :, 1, None] * e2[:, None, :]   # (B, M, 3)
    o_l = 0.5 * rig.beam_exit_mm * lat
    d_l = d[:, None, :] + 0.5e-3 * rig.beam_divergence_mrad * lat
    d_l /= np.linalg.norm(d_l, axis=2, keepdims=True)
    refl = reflectivity_table(rig)
    # coarse probe: the centre and 6 sub-rays on the outer ring; beams whose probes all hit the
    # same surface are taken as fully on it (their range: the probes' energy-weighted mean)
    ring = np.flatnonzero(np.isclose(np.linalg.norm(s, axis=1), 1.0))
    probe = np.concatenate([[0], ring[:: max(1, len(ring) // 6)]])
    out = np.zeros((P, B))
    for p0 in range(0, P, 8):
        Rc, Tc = R[p0:p0 + 8], T[p0:p0 + 8]
        n = len(Rc)
        t, idx, e = _cast(surfaces, Rc, Tc, o_l[:, probe], d_l[:, probe], wgt[probe], refl, rig)
        full = np.any(idx != idx[:, :, :1], axis=2)                       # (n, B) mixed beams
        ew = np.where(idx >= 0, e, 0.0)
        with np.errstate(invalid="ignore", divide="ignore"):
            res = np.where(idx[:, :, 0] >= 0, (ew * t).sum(2) / ew.sum(2), 0.0)
            # energy of a uniform footprint ~ the probes' mean energy per unit weight
            tot = ew.sum(2) / wgt[probe].sum()
        res = np.where(tot >= rig.detect_energy, res, 0.0)
        pi, bi = np.nonzero(full)
        if len(pi):
            o_sub = o_l[bi]                      # (F, M, 3)
            d_sub = d_l[bi]
            dirs = np.einsum("fij,fmj->fmi", Rc[pi], d_sub).reshape(-1, 3)
            orig = (np.einsum("fij,fmj->fmi", Rc[pi], o_sub) + Tc[pi][:, None, :]).reshape(-1, 3)
            tf, idf = trace(surfaces, dirs, origins=orig)
            tf, idf, ef = _energy(surfaces, tf, idf, orig, dirs, np.tile(wgt, len(pi)), refl, rig)
            res[pi, bi] = echo(tf.reshape(len(pi), M), idf.reshape(len(pi), M), ef.reshape(len(pi), M),
                                len(surfaces), rig)
        out[p0:p0 + n] = res
    out = apply_ranging_errors(out, rig, "offset")
    ok = out > 0
    out = out + ok * rng.normal(0.0, rig.range_noise_mm, out.shape)
    if rig.range_noise_rel > 0:          # a cheap scanner: noise growing with the range
        out = out + ok * rng.normal(0.0, 1.0, out.shape) * rig.range_noise_rel * out
    if rig.spurious_rate > 0:
        spur = rng.random(out.shape) < rig.spurious_rate
        out[spur] = rng.uniform(rig.lidar_range_min_mm, rig.lidar_range_max_mm, int(spur.sum()))
    if rig.drop_rate > 0:
        out[rng.random(out.shape) < rig.drop_rate] = 0.0
    out = apply_ranging_errors(out, rig, "quantise")
    out[(out < rig.lidar_range_min_mm) | (out > rig.lidar_range_max_mm)] = 0.0
    return np.round(out, 1)
