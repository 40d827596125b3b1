"""The disc's edge response: an edge model, calibrated on reference discs or taken from a prior.

:func:`lidarcal.measure.measure_disc` places the rim where half of the beam's
spot is on the disc (the half-share crossing). That is exact for a symmetric
spot with energy-weighted mixed ranges, but a real scanner's edge response is
unknown until measured: a first-echo scanner that reports the disc once a
quarter of its spot is on it sees the disc larger by a fraction of the spot;
unequal reflectivities move the half-energy point. Whatever the physics, the
result is a radial offset of the detected rim that scales with the beam's
footprint at the disc, the same for discs of any size.

Two parts of that response depend on the disc's pose and are modelled, not
left to the edge model (each moved a calibrated diameter by up to ~0.1 mm
between discs of one rig, several times the fit's sigma):

* the energy ratio: a diffuse (Lambertian) surface returns energy in
  proportion to ``cos(incidence)``, so a tilted disc in front of a wall
  returns less than a disc facing the beam; mixed ranges are read with that
  ratio (:func:`edge_footprint`, :class:`lidarcal.measure.Footprint`
  ``lambertian``); the disc's albedo against the background's stays unknown
  and is part of ``k``;
* foreshortening: the offset is a distance across the beam; on a disc tilted
  by ``i`` it is up to ``1 / cos i`` longer in the disc plane where the rim
  runs across the tilt. The *rim stretch* ``s`` (``DiscMeasurement.info
  ["rim_stretch"]``, >= 1) is its mean over the rim crossings as the circle
  fit weighs them.

Edge model (``type: "offset_beam_spacing"``)
-------------------------------------------
The detected rim lies ``delta = k * u`` outside the true rim, with ``u`` the
beam spacing at the disc, ``u = rho * angle_step`` (``rho`` the range from the
LiDAR to the disc centre at the middle of the sweep, ``angle_step`` the
LiDAR's beam step in radians): the one footprint scale every dataset states
(the beam divergence is not in the data; scanners are built with spots of
the order of their beam step). So::

    D = D_half - 2 k u s,    sigma_D^2 = sigma_fit^2 + (2 u s sigma_k)^2 + (c sigma_offset)^2

``D_half`` the half-share diameter, ``sigma_fit`` its random uncertainty (the
larger of the least-squares sigma and a sector bootstrap of the rim
crossings, :func:`random_sigma_mm`), ``u s`` the *edge spacing*. The last
term is the calibration's range offset (``calibration.json`` ``ranging``
``offset_sigma_mm``, :mod:`lidarcal.ranging`): an offset error ``e`` scales a
disc at range ``rho`` across the beams by ``-e / rho`` (``dD = -D e / rho`` for a disc facing
the LiDAR) and, through the references, ``k``; ``c`` is the sum (:func:`offset_sensitivity`). The pose
function's own covariance moves a diameter by < 0.001 mm (a rigid error of the
LiDAR pose; measured on simulated rigs against the true poses) and is left out.

- **Reference** (``source: "reference"``): discs of known diameter measured on
  the same rig give ``k_i = (D_half,i - D_ref,i) / (2 u_i s_i)``; ``k`` is their
  mean, ``sigma_k`` the larger of the propagated fit uncertainty and (with
  three or more references) the standard error of their spread; the sigma of
  a disc at another range adds ``k |u s - u_ref s_ref|`` (:meth:`EdgeModel.apply`);
  with three or more references the spread beyond their fits (``k_scatter``,
  each disc's own edge response) enters every disc's sigma as ``2 u s k_scatter``.
- **Prior** (``source: "prior"``, no reference): ``k`` uniform on an interval
  (mean the centre, ``sigma_k = width / sqrt(12)``) chosen by what the rim
  shows. The *mixed share* is the fraction of rim crossings whose outer beam
  is a mixed range (between disc and background) rather than a clean miss;
  its median over the dataset's discs tells the echo physics:

  * mixed share >= 0.6, an energy-mixing scanner (mixed ranges are what it
    reports): its half-share edge is unbiased for a symmetric spot and equal
    reflectivities; spot asymmetry and a brighter disc move it outwards:
    ``k`` on ``[0, 0.3]``;
  * otherwise a first-echo scanner with an unknown detection threshold: 0
    for a threshold at half the spot, 0.6 for a first echo at about a quarter
    of a spot 1.5-2 beam spacings wide: ``k`` on ``[0, 0.6]``.

  The edge model's uncertainty then dominates ``diameter_sigma_mm``, so that
  the true diameter lies within 2 sigma for the scanners in that range.

Wide spot (no reference)
------------------------
Both priors assume a spot about a beam spacing wide. A wider spot (large exit window or
divergence) moves the half-share rim by a fraction of the *spot*, not of the beam spacing:
a disc ``kappa`` times as bright per unit area as its background puts the half-energy point
``sigma_r Phi^-1(kappa / (1 + kappa))`` outside the rim (0.2 spot sigmas for 1.4x), and
``kappa`` cannot be read from ranges. :func:`lidarcal.measure.measure_disc` measures the
spot's sigma in the disc's own mixed returns (:mod:`lidarcal.spot`, ``info["spot_sigma_mm"]``);
where it exceeds :data:`WIDE_SPOT_SPACINGS` beam spacings, that disc's ``k`` is uniform on
:data:`PRIOR_SPOT_SIGMAS` spot sigmas: a disc as bright as its background per unit area
up to twice as bright, ``Phi^-1(2/3) = 0.431`` (the narrow mixed prior's direction: a brighter
disc moves the rim outwards); a darker disc or a much darker background (black cloth) lies
outside it. A warning names the discs, the spot and the cure (``--reference``).
A first-echo rim shows no mixed returns; when the calibration's scan edge zones
(``calibration.json`` ``scan_edge_zones``) are ``n`` returns deep, a spot that wide at the V,
the prior's upper end becomes ``n`` beam spacings, with the same warning.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from . import paper

#: prior edge offset, beam spacings, uniform on these intervals (module docstring)
PRIOR_K_FIRST_ECHO = (0.0, 0.6)
PRIOR_K_MIXED = (0.0, 0.3)
#: median mixed share at or above which the scanner is taken as energy-mixing
MIXED_SHARE_MIN = 0.6
#: a reference that implies an offset outside this range (beam spacings) is suspect
PLAUSIBLE_K = (-0.5, 1.5)
#: wide spot, no reference: rim offset prior in the spot's sigmas (module docstring, "Wide spot")
PRIOR_SPOT_SIGMAS = (0.0, 0.431)
#: a spot whose sigma across the beam exceeds this many beam spacings is wide
WIDE_SPOT_SPACINGS = 1.0


@dataclass(frozen=True)
class EdgeModel:
    """Radial offset of the detected rim, ``delta = k * u`` (u: beam spacing at the disc, mm)."""

    k: float
    k_sigma: float
    source: str  # "prior" | "reference"
    echo: str = "unknown"  # what the rim shows: "mixed" | "first-echo" | "unknown"
    references: tuple[str, ...] = ()
    k_references: tuple[float, ...] = ()
    spacing_ref_mm: float | None = None  # mean edge spacing at the reference discs
    k_scatter: float = 0.0  # disc-to-disc scatter of k beyond the fits (>= 3 references), 1-sigma
    warnings: tuple[str, ...] = field(default=(), compare=False)

    @staticmethod
    def prior(mixed_share: float | None = None) -> EdgeModel:
        """No reference: uniform prior in beam spacings, chosen by the median mixed share."""
        mixed = mixed_share is not None and np.isfinite(mixed_share) and mixed_share >= MIXED_SHARE_MIN
        lo, hi = PRIOR_K_MIXED if mixed else PRIOR_K_FIRST_ECHO
        echo = "unknown" if mixed_share is None or not np.isfinite(mixed_share) else \
            ("mixed" if mixed else "first-echo")
        return EdgeModel(0.5 * (lo + hi), (hi - lo) / np.sqrt(12.0), "prior", echo=echo)

    def for_disc(self, spot_sigma_spacings: float, zone_spacings: float = 0.0) -> EdgeModel:
        """The prior widened to one disc's beam spot (module docstring, "Wide spot"): a spot
        sigma measured in its mixed returns above :data:`WIDE_SPOT_SPACINGS` beam spacings
        makes ``k`` uniform on :data:`PRIOR_SPOT_SIGMAS` x that sigma; no spot measured (no
        mixed returns) but the calibration's scan edge zones ``zone_spacings`` returns deep
        (a wide spot at the V) makes the upper end that depth. References: unchanged."""
        if self.source != "prior":
            return self
        half = 0.5 * np.sqrt(12.0) * self.k_sigma  # the uniform prior's half width
        lo, hi = self.k - half, self.k + half
        if np.isfinite(spot_sigma_spacings) and spot_sigma_spacings > WIDE_SPOT_SPACINGS:
            lo, hi = (v * spot_sigma_spacings for v in PRIOR_SPOT_SIGMAS)
        elif not np.isfinite(spot_sigma_spacings) and zone_spacings > hi:
            hi = float(zone_spacings)
        else:
            return self
        return replace(self, k=0.5 * (lo + hi), k_sigma=(hi - lo) / np.sqrt(12.0))

    def apply(self, diameter_half_mm: float, fit_sigma_mm: float, spacing_mm: float) -> tuple[float, float]:
        """Corrected diameter and its 1-sigma (mm): ``D_half - 2 k u s``, module docstring;
        ``spacing_mm`` is the edge spacing ``u s`` (:func:`edge_spacing_mm`).

        From references, a third term covers the offset's unknown scaling with
        range: ``k u`` (a spot growing with range) against a constant ``k u_ref``
        (a spot set by the exit aperture) differ by ``2 k |u - u_ref|`` in
        diameter; half of it enters the sigma.
        """
        d = diameter_half_mm - 2.0 * self.k * spacing_mm
        s = np.hypot(fit_sigma_mm, 2.0 * spacing_mm * self.k_sigma)
        if self.spacing_ref_mm is not None:
            s = np.hypot(s, abs(self.k) * abs(spacing_mm - self.spacing_ref_mm))
        s = np.hypot(s, 2.0 * spacing_mm * self.k_scatter)
        return float(d), float(s)

    def to_dict(self) -> dict:
        return {"type": "offset_beam_spacing", "source": self.source, "echo": self.echo, "k": self.k,
                "k_sigma": self.k_sigma, "k_scatter": self.k_scatter, "references": list(self.references),
                "k_references": list(self.k_references), "beam_spacing_ref_mm": self.spacing_ref_mm,
                "formula": "diameter_mm = diameter_half_mm - 2 k edge_spacing_mm; "
                           "edge_spacing_mm = beam_spacing_mm x rim_stretch; "
                           "beam_spacing_mm = range to the disc x angle step (rad)"}


def edge_footprint():
    """The :class:`lidarcal.measure.Footprint` discs are measured with: diffuse surfaces, the
    energy ratio of disc and background scaled by their ``cos(incidence)`` (module docstring)."""
    from .measure import Footprint  # lazy: measure imports pandas and scipy

    return Footprint(lambertian=True)


def random_sigma_mm(measurement, sectors: int = 12, n_boot: int = 200, seed: int = 0) -> float:
    """1-sigma of the half-share diameter from its rim crossings, by a sector (block) bootstrap.

    The crossings of neighbouring scan lines share the rim's phase against the
    beam grid, so their errors are correlated and the least-squares sigma
    (``DiscMeasurement.diameter_std_mm``) is too small. Here the kept
    crossings are grouped in ``sectors`` equal angular sectors around the
    centre; sectors are resampled with replacement and the circle refitted
    (Kasa's algebraic fit, :func:`lidarcal.geometry.fit_circle_2d_algebraic`);
    the spread of the diameters is returned (0 when too few crossings).
    """
    from .geometry import fit_circle_2d_algebraic, plane_basis

    q = np.asarray(measurement.crossings, float)[np.asarray(measurement.crossing_inlier, bool)]
    if len(q) < 3 * sectors:
        return 0.0
    B = plane_basis(np.asarray(measurement.normal, float))
    xy = (q - np.asarray(measurement.center_mm, float)) @ B.T
    sec = np.minimum(((np.arctan2(xy[:, 1], xy[:, 0]) + np.pi) / (2 * np.pi) * sectors).astype(int),
                     sectors - 1)
    groups = [np.flatnonzero(sec == k) for k in range(sectors)]
    groups = [g for g in groups if len(g)]
    rng = np.random.default_rng(seed)
    d = []
    for _ in range(n_boot):
        pick = np.concatenate([groups[i] for i in rng.integers(0, len(groups), len(groups))])
        try:
            d.append(2.0 * fit_circle_2d_algebraic(xy[pick])[1])
        except (ValueError, np.linalg.LinAlgError):
            continue
    return float(np.std(d, ddof=1)) if len(d) > 10 else 0.0


def mixed_share(info: dict) -> float:
    """Share of rim crossings whose outer beam is a mixed range, from ``DiscMeasurement.info``."""
    n = info.get("crossings", 0)
    return float(1.0 - info.get("hard_crossings", 0) / n) if n else float("nan")


def beam_spacing_mm(center_mm: np.ndarray, lidar_origin_mm: np.ndarray, angle_step_deg: float) -> float:
    """Beam spacing at the disc, ``u = rho * angle_step`` (mm), the edge model's unit."""
    rho = float(np.linalg.norm(np.asarray(center_mm, float) - np.asarray(lidar_origin_mm, float)))
    return rho * np.radians(angle_step_deg)


def edge_spacing_mm(measurement, lidar_origin_mm: np.ndarray, angle_step_deg: float) -> float:
    """The edge model's unit on this disc, ``u s``: beam spacing times rim stretch (module
    docstring; ``s`` from ``measurement.info["rim_stretch"]``, 1 when absent)."""
    s = float(measurement.info.get("rim_stretch", 1.0))
    return beam_spacing_mm(measurement.center_mm, lidar_origin_mm, angle_step_deg) * s


def doubted_offset_sigma(cal) -> float:
    """The range offset's sigma (mm) for the diameters: ``calibration.json`` ``ranging``
    ``offset_sigma_mm``, and ``hypot(sigma, |offset|)`` when the calibration widened its
    sigmas to the rigid fit (``sigma.widened_to_rigid``): the joint fit and the rigid fit (raw
    ranges) then disagree, e.g. a range bias growing with the incidence angle read as an offset
    (:func:`lidarcal.calibration_checks.joint_rigid_warnings`), so the offset applied to the sweeps may
    be wrong by itself (combo3 ``disc_incidence10``: a -9.2 +- 0.8 mm offset, 300 mm discs
    0.9-1.1 mm off at 1.7-2.1 sigma)."""
    from .ranging import ranging_of

    rng = ranging_of(cal)
    data = getattr(cal, "data", None) or {}
    widened = bool((data.get("sigma") or {}).get("widened_to_rigid"))
    return float(np.hypot(rng.offset_sigma_mm, rng.offset_mm) if widened else rng.offset_sigma_mm)


def offset_sensitivity(diameter_mm: np.ndarray, range_mm: np.ndarray, spacing_mm: np.ndarray,
                       reference: np.ndarray, cos_incidence: np.ndarray | float = 1.0) -> np.ndarray:
    """d(diameter)/d(range offset error) of each disc after the edge model (module docstring).

    An offset error ``e`` moves every return along its beam: the disc's extent across the
    beams scales by ``-e / rho``, its extent along them (``D sin i`` for a disc tilted by ``i``)
    does not; the circle averages the two directions: ``a = -D (1 + cos^2 i) / (2 rho)``.
    With references (``reference`` True), ``k`` is the mean of ``(D_half - D_ref) / (2 u s)``
    and moves by ``mean(a_r / (2 u_r s_r)) e``, so ``c = a - u s mean(a_r / (u_r s_r))``;
    without, ``c = a`` (the prior ``k`` does not depend on the data).
    """
    a = -np.asarray(diameter_mm, float) * (1.0 + np.asarray(cos_incidence, float) ** 2) \
        / (2.0 * np.asarray(range_mm, float))
    u = np.asarray(spacing_mm, float)
    ref = np.asarray(reference, bool)
    return a - u * np.mean(a[ref] / u[ref]) if ref.any() else a


def fit_edge_model(names: list[str], diameter_half_mm: np.ndarray, fit_sigma_mm: np.ndarray,
                   spacing_mm: np.ndarray, reference_mm: np.ndarray) -> EdgeModel:
    """Edge offset ``k`` from reference discs of known diameter (module docstring).

    Each reference gives ``k_i = (D_half,i - D_ref,i) / (2 u_i s_i)`` (``spacing_mm``: the edge
    spacings ``u s``, :func:`edge_spacing_mm`); returns their
    mean with ``sigma_k`` = max(propagated fit sigma, spread / sqrt(n) for n >= 3); with n >= 3
    also ``k_scatter``, the spread beyond the fits' (``sqrt(max(spread^2 - mean(sigma_i^2), 0))``):
    each disc's own deviation from ``k``, added to every measured disc's sigma (one or two
    references cannot show it: between six discs of a simulated paper rig, noise averaged out,
    ``k`` spread by 0.006 beam spacings).
    A ``k`` outside :data:`PLAUSIBLE_K` or references that disagree by more
    than 4 sigma are reported in ``warnings`` (a wrong reference diameter?).
    """
    d = np.asarray(diameter_half_mm, float)
    s = np.asarray(fit_sigma_mm, float)
    u = np.asarray(spacing_mm, float)
    ref = np.asarray(reference_mm, float)
    if len(d) == 0:
        raise ValueError("fit_edge_model needs at least one reference disc")
    ki = (d - ref) / (2.0 * u)
    si = s / (2.0 * u)
    k = float(np.mean(ki))
    ks = float(np.sqrt(np.sum(si**2)) / len(ki))
    tau = 0.0
    warns = []
    if len(ki) >= 2:
        spread = float(np.std(ki, ddof=1))
        if len(ki) >= 3:
            ks = max(ks, spread / np.sqrt(len(ki)))
            # the discs' own edge responses differ (seen as spread beyond their fits): a
            # measured disc carries that scatter too, not only the mean's standard error
            tau = float(np.sqrt(max(spread**2 - np.mean(si**2), 0.0)))
        if spread > 4.0 * max(float(np.sqrt(np.mean(si**2))), 0.02):
            warns.append(f"the reference discs disagree: edge offsets {', '.join(f'{v:.3f}' for v in ki)} "
                         "beam spacings; check their reference_diameter_mm")
    if not PLAUSIBLE_K[0] <= k <= PLAUSIBLE_K[1]:
        warns.append(f"the references imply a rim offset of {k:.2f} beam spacings, outside the plausible "
                     f"{PLAUSIBLE_K[0]:g}..{PLAUSIBLE_K[1]:g}; check their reference_diameter_mm and units")
    return EdgeModel(k, ks, "reference", references=tuple(names),
                     k_references=tuple(float(v) for v in ki), spacing_ref_mm=float(np.mean(u)),
                     k_scatter=tau,
                     warnings=tuple(warns))


def measure_dataset(dataset, calibration, references: list[str] | None = None):
    """Every disc of dataset.json ``measurements`` (section 3.2) with its edge model applied.

    ``calibration``: a ``calibration.json`` path or a pose function
    (``.pose(psi_deg)``). ``references``: names of measurements whose ``reference_diameter_mm`` is
    trusted to calibrate the edge model (:func:`fit_edge_model`); without, the
    prior (:meth:`EdgeModel.prior`). Returns a DataFrame, one row per disc;
    ``attrs["edge_model"]`` holds the model, ``attrs["warnings"]`` its warnings.
    """
    import pandas as pd

    from .api import load_calibration
    from .io.dataset import DatasetError, load_dataset, read_sweep
    from .measure import measure_disc

    ds = load_dataset(dataset)
    cal = calibration if hasattr(calibration, "pose") else load_calibration(calibration)
    if not ds.measurements:
        raise DatasetError(ds.dataset_json, "lists no 'measurements' to measure; add the sweeps "
                                            "(name, sweep file) to it, see docs/dataset-format.md")
    specs = {m.name: m for m in ds.measurements}
    refs = list(dict.fromkeys(references or []))
    for name in refs:
        if name not in specs:
            raise DatasetError(ds.dataset_json, f"--reference {name}: no measurement of that name; "
                                                f"known: {', '.join(specs)}")
        if specs[name].reference_diameter_mm is None:
            raise DatasetError(ds.dataset_json, f"--reference {name}: its reference_diameter_mm is not "
                                                "given; a reference needs its known diameter")
    if refs and len(refs) == len(specs):
        raise DatasetError(ds.dataset_json, "every measurement is a --reference; leave at least one "
                                            "to measure")
    rows = []
    for m in ds.measurements:
        if m.object != "disc":
            raise DatasetError(ds.dataset_json, f"measurement '{m.name}': object '{m.object}' is not "
                                                "supported (only 'disc')")
        sweep = read_sweep(m.sweep, ds.lidar)
        try:
            r = measure_disc(sweep, cal, ds.lidar, footprint=edge_footprint())
        except ValueError as e:
            raise DatasetError(m.sweep, str(e)) from None
        origin = cal.pose(float(np.median(sweep["psi_deg"].to_numpy(float)))).T
        rows.append({"name": m.name, "reference_diameter_mm": m.reference_diameter_mm,
                     "reference": m.name in refs, "diameter_half_mm": r.diameter_mm,
                     "fit_sigma_mm": max(r.diameter_std_mm, random_sigma_mm(r)),
                     "beam_spacing_mm": beam_spacing_mm(r.center_mm, origin, ds.lidar.angle_step_deg),
                     "rim_stretch": float(r.info["rim_stretch"]),
                     "edge_spacing_mm": edge_spacing_mm(r, origin, ds.lidar.angle_step_deg),
                     "range_mm": float(np.linalg.norm(r.center_mm - origin)),
                     "cos_incidence": float(abs(r.normal @ (r.center_mm - origin))
                                            / np.linalg.norm(r.center_mm - origin)),
                     "center_mm": r.center_mm.tolist(), "normal": r.normal.tolist(),
                     "points": int(r.points), "naive_diameter_mm": r.naive_diameter_mm,
                     "mixed_share": mixed_share(r.info),
                     "spot_sigma_mm": float(r.info.get("spot_sigma_mm", np.nan))})
    if refs:
        sel = [row for row in rows if row["reference"]]
        edge = fit_edge_model([row["name"] for row in sel],
                              np.array([row["diameter_half_mm"] for row in sel]),
                              np.array([row["fit_sigma_mm"] for row in sel]),
                              np.array([row["edge_spacing_mm"] for row in sel]),
                              np.array([row["reference_diameter_mm"] for row in sel]))
        edge = replace(edge, echo=EdgeModel.prior(float(np.median([row["mixed_share"] for row in rows]))).echo)
        edge = _unseen_spot_references(edge, rows, _edge_zone_returns(calibration))
    else:
        edge = EdgeModel.prior(float(np.median([row["mixed_share"] for row in rows])))
    offset_sigma = doubted_offset_sigma(cal)
    sens = offset_sensitivity([row["diameter_half_mm"] for row in rows], [row["range_mm"] for row in rows],
                              [row["edge_spacing_mm"] for row in rows], [row["reference"] for row in rows],
                              [row["cos_incidence"] for row in rows])
    zone = _edge_zone_returns(calibration)
    out, wide = [], []
    for row, c in zip(rows, sens):
        spot_u = row["spot_sigma_mm"] / row["beam_spacing_mm"]
        e = edge.for_disc(spot_u, zone)
        if e is not edge:
            wide.append((row["name"], spot_u, 2.0 * row["edge_spacing_mm"] * e.k_sigma))
        d, s = e.apply(row["diameter_half_mm"], row["fit_sigma_mm"], row["edge_spacing_mm"])
        s = float(np.hypot(s, c * offset_sigma))
        ref = row["reference_diameter_mm"]
        out.append({"name": row["name"], "diameter_mm": d, "diameter_sigma_mm": s,
                    "reference_diameter_mm": ref, "error_mm": None if ref is None else d - ref,
                    "reference": row["reference"],
                    "center_mm": row["center_mm"], "normal": row["normal"], "points": row["points"],
                    "naive_diameter_mm": row["naive_diameter_mm"],
                    "diameter_half_mm": row["diameter_half_mm"], "beam_spacing_mm": row["beam_spacing_mm"],
                    "rim_stretch": row["rim_stretch"], "edge_spacing_mm": row["edge_spacing_mm"],
                    "edge_offset_mm": e.k * row["edge_spacing_mm"], "mixed_share": row["mixed_share"],
                    "spot_sigma_mm": row["spot_sigma_mm"] if np.isfinite(row["spot_sigma_mm"]) else None})
    table = pd.DataFrame(out)
    # the range offset's 1-sigma (calibration.json ranging) propagated into every diameter
    table.attrs["edge_model"] = {**edge.to_dict(), "range_offset_sigma_mm": offset_sigma,
                                 "wide_spot": [name for name, _, _ in wide]}  # their own k: edge_offset_mm
    table.attrs["warnings"] = (_other_rig_warnings(ds, calibration) + list(edge.warnings)
                               + _wide_spot_warnings(wide, zone))
    return table


def _unseen_spot_references(edge: EdgeModel, rows: list[dict], zone: float) -> EdgeModel:
    """References on a rig whose calibration found scan edge zones ``zone`` returns deep while
    no disc rim shows mixed returns (a wide first-echo spot): a ``k`` up to the zone depth is
    that spot, not a wrong reference diameter; but the first echo's offset changes with the
    rim's curvature (not modelled), so discs of another size than every reference (> 20 %)
    are named in a warning (measured on a simulated 10 mrad first-echo rig: 300 mm discs
    against a 100 mm reference 0.7-1.6 mm large, outside their 2 sigma)."""
    if zone <= 0 or any(np.isfinite(r["spot_sigma_mm"]) for r in rows):
        return edge
    warns = [w for w in edge.warnings if not (edge.k <= zone and "outside the plausible" in w)]
    refs = [r["diameter_half_mm"] for r in rows if r["reference"]]
    other = [r["name"] for r in rows if not r["reference"]
             and all(abs(r["diameter_half_mm"] / d - 1.0) > 0.2 for d in refs)]
    if other:
        warns.append(f"{', '.join(other)}: the calibration's scan edge zones ({zone:g} returns, calibration.json "
                     "scan_edge_zones) show a wide spot and the rims show no mixed returns (a first-echo "
                     "scanner), whose rim offset changes with the disc's size; these differ from every "
                     "reference by more than 20 %: measure them against a reference disc of about their size")
    return replace(edge, warnings=tuple(warns))


def _edge_zone_returns(calibration) -> float:
    """Depth (returns) of the calibration's scan edge zones (``calibration.json``
    ``scan_edge_zones``, :mod:`lidarcal.scan_edges`): > 0 when the V's scans showed a spot
    wider than a beam spacing; 0 when none were found or not recorded."""
    import json

    if hasattr(calibration, "pose"):
        return 0.0
    try:
        z = json.loads(Path(calibration).read_text()).get("scan_edge_zones") or {}
    except (OSError, ValueError):
        return 0.0
    return float(max(z.get("outer_returns") or 0, z.get("hinge_returns") or 0))


def _wide_spot_warnings(wide: list[tuple[str, float, float]], zone: float) -> list[str]:
    """One warning naming the discs whose prior was widened to a wide beam spot, and why."""
    if not wide:
        return []
    names = ", ".join(n for n, _, _ in wide)
    spread = max(s for _, _, s in wide)
    seen = [u for _, u, _ in wide if np.isfinite(u)]
    span = f"{min(seen):.1f}" if seen and f"{min(seen):.1f}" == f"{max(seen):.1f}" else \
        (f"{min(seen):.1f}-{max(seen):.1f}" if seen else "")
    cause = (f"the beam spot's sigma is {span} beam spacings at the discs "
             "(measured in their mixed rim returns)") if seen else (
        f"the calibration's scan edge zones ({zone:g} returns, calibration.json scan_edge_zones) show a "
        "spot wider than a beam spacing and the discs' rims show no mixed returns to measure it")
    msg = (f"{names}: {cause}; the rim offset of such a spot is not known without a reference, so "
           f"each diameter_sigma_mm carries up to {spread:.2f} mm (1-sigma) for it; measure a disc "
           "of known diameter on the same rig and pass it with --reference NAME")
    return [msg]


def _other_rig_warnings(ds, calibration) -> list[str]:
    """A ``calibration.json`` made from another dataset folder, or with another camera, measures
    this one only if the rig is the same and has not moved: say so (eq. 28 trusts the pose)."""
    import json
    import os

    if hasattr(calibration, "pose"):
        return []
    try:
        cal = json.loads(Path(calibration).read_text())
    except (OSError, ValueError):
        return []
    src = cal.get("dataset")
    if not isinstance(src, str) or os.path.realpath(src) == os.path.realpath(ds.root):
        return []
    cam, own = cal.get("camera") or {}, ds.camera
    same_camera = own is None or not cam.get("K") or (
        list(cam.get("image_size", [])) == list(own.image_size)
        and np.allclose(np.asarray(cam["K"], float), own.K, rtol=1e-6, atol=1e-6))
    return [f"{calibration}: made from another dataset ({src})"
            + ("" if same_camera else " with another camera (K or image_size differ)")
            + f"; measuring {ds.root} with it assumes the same rig, unmoved since that calibration"]


def table2_columns(measurements: dict) -> dict[str, list]:
    """Table 2 columns from a ``measurements.json`` dict: name, diameter, 1-sigma, reference, error.

    For the report's Table 2: ``diameter_sigma_mm`` is the 1-sigma including
    the edge model; ``reference`` marks the discs that calibrated it (their
    error is not a test).
    """
    rows = measurements.get("measurements", [])
    return {"name": [r["name"] for r in rows],
            "diameter_mm": [r["diameter_mm"] for r in rows],
            "diameter_sigma_mm": [r.get("diameter_sigma_mm") for r in rows],
            "reference_diameter_mm": [r.get("reference_diameter_mm") for r in rows],
            "error_mm": [r.get("error_mm") for r in rows],
            "reference": [bool(r.get("reference", False)) for r in rows]}


# ------------------------------------------------------------------ notebook 06's tables

#: the paper's Table 2 summary (section 3.2: 140 mm disc, mean of its trials), mm
#: the paper's Table 2 summary (lidarcal.paper)
PAPER_TABLE2 = {"mean diameter": paper.TABLE2_MEAN[0],
                "mean error": paper.TABLE2_MEAN[0] - paper.REFERENCE_MM,
                "mean abs error": paper.TABLE2_MEAN[1]}


def reference_choice(ds) -> str | None:
    """The measurement to calibrate the edge model with: the first one of dataset.json
    ``measurements`` with a ``reference_diameter_mm``, when at least one other is left to
    measure (:func:`measure_dataset` refuses to measure none); ``None``: prior mode only."""
    if len(ds.measurements) < 2:
        return None
    return next((m.name for m in ds.measurements if m.reference_diameter_mm is not None), None)


def table2(measured: dict, ds, truth: dict | None = None):
    """Table 2 (section 3.2) of the half-share fits, one row per trial.

    ``measured``: name -> :class:`lidarcal.measure.DiscMeasurement`. The reference is the true
    diameter where ``truth`` (truth.json) has the trial, else its ``reference_diameter_mm``
    (errors NaN without either); ``centre_error_mm`` only with truth. Columns: trial,
    reference_mm, measured_mm, error_mm, naive_mm, naive_error_mm, [centre_error_mm], points.
    """
    import pandas as pd

    t_true = {t["name"]: t for t in (truth or {}).get("measurements", [])}
    specs = {m.name: m for m in ds.measurements}
    rows = []
    for name, m in measured.items():
        ref = t_true[name]["diameter_mm"] if name in t_true else specs[name].reference_diameter_mm
        row = {"trial": name, "reference_mm": np.nan if ref is None else float(ref),
               "measured_mm": m.diameter_mm, "naive_mm": m.naive_diameter_mm}
        row["error_mm"] = row["measured_mm"] - row["reference_mm"]
        row["naive_error_mm"] = row["naive_mm"] - row["reference_mm"]
        if name in t_true:
            row["centre_error_mm"] = float(np.linalg.norm(m.center_mm - np.asarray(t_true[name]["center_mm"])))
        row["points"] = m.points
        rows.append(row)
    cols = ["trial", "reference_mm", "measured_mm", "error_mm", "naive_mm", "naive_error_mm",
            *(["centre_error_mm"] if t_true else []), "points"]
    return pd.DataFrame(rows, columns=cols)


def table2_summary(t2):
    """Table 2's means beside the paper's: mean diameter, mean error and mean absolute error of
    the naive boundary circle and of the hits + misses fit (errors over the trials with a
    reference; NaN without any)."""
    import pandas as pd

    def stats(d, e):
        return {"mean diameter": d.mean(), "mean error": e.mean(), "mean abs error": e.abs().mean()}

    return pd.DataFrame({"paper (Table 2)": PAPER_TABLE2,
                         "naive boundary circle": stats(t2.naive_mm, t2.naive_error_mm),
                         "hits + misses (ours)": stats(t2.measured_mm, t2.error_mm)})


def checked_errors(table):
    """The errors of a :func:`measure_dataset` table that test it: float ``error_mm`` of the discs
    with a known diameter that did not calibrate the edge model (a Series by name)."""
    import pandas as pd

    err = pd.to_numeric(table["error_mm"], errors="coerce").astype(float)
    keep = err.notna() & ~table["reference"].astype(bool)
    return err[keep].set_axis(table["name"][keep])


def edge_model_table(prior, with_reference=None, reference: str | None = None):
    """The discs measured with the prior edge model and, when a reference was chosen, with
    ``reference`` calibrating it, side by side (both :func:`measure_dataset` tables)."""
    import pandas as pd

    cols = {"no reference: diameter_mm": prior.diameter_mm, "sigma_mm": prior.diameter_sigma_mm,
            "error_mm": pd.to_numeric(prior.error_mm, errors="coerce")}
    if with_reference is not None:
        cols.update({f"reference {reference}: diameter_mm": with_reference.diameter_mm,
                     "sigma_mm ": with_reference.diameter_sigma_mm,
                     "error_mm ": pd.to_numeric(with_reference.error_mm, errors="coerce"),
                     "is reference": with_reference.reference})
    return pd.DataFrame(cols).set_axis(prior.name)
