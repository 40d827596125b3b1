"""Rig presets for the simulator: every number that describes a rig lives in :class:`RigConfig`.

Ranges are ``(low, high)`` tuples sampled uniformly per seed; scalars are fixed
properties of the hardware. Lengths in mm, angles in degrees, image levels in
DN (8-bit digital numbers).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

Range = tuple[float, float]


@dataclass(frozen=True)
class RigConfig:
    """Every parameter of a simulated rig (camera, boards, LiDAR, turntable, rendering, nuisances)."""

    name: str
    # --- camera (OpenCV model) ---
    image_size: tuple[int, int]                    # (width, height) px
    K: tuple[tuple[float, float, float], ...]      # 3 x 3
    dist: tuple[float, ...]                        # k1, k2, p1, p2, k3
    camera_in_dataset: bool = True                 # write "camera" into dataset.json
    # --- intrinsics chessboard views ---
    intrinsics_inner_corners: tuple[int, int] = (9, 6)
    intrinsics_square_mm: float = 25.0
    n_intrinsics_views: int = 12
    intrinsics_tilt_deg: float = 40.0              # max board tilt from fronto-parallel
    intrinsics_fill: Range = (0.35, 0.65)          # board width / image width
    # --- V-board ---
    v_inner_corners: tuple[int, int] = (14, 20)    # [per_row, per_column]; long side vertical
    v_square_mm: float = 20.0
    v_margin_squares: float = 1.0                  # white margin around each chessboard
    v_angle_deg: Range = (110.0, 130.0)            # opening angle of the V
    hinge_distance_mm: Range = (1220.0, 1320.0)    # camera to hinge (z)
    v_yaw_deg: float = 6.0                         # max yaw of the V's bisector
    v_tilt_deg: float = 2.5                        # max tilt of the hinge from camera y
    image_border_px: float = 8.0                   # whole boards at least this far inside the image
    wall_distance_mm: Range = (2300.0, 3400.0)     # background wall (z), behind the V
    wall_tilt_deg: float = 10.0
    wall_min_gap_mm: float = 400.0                 # wall at least this far behind the hinge (z)
    post_radius_mm: Range = (12.0, 25.0)           # stand under the hinge and a pole beside the V
    # --- LiDAR ---
    lidar_angle_min_deg: float = -35.0
    lidar_angle_max_deg: float = 35.0
    lidar_angle_step_deg: float = 0.083333
    lidar_range_min_mm: float = 700.0
    lidar_range_max_mm: float = 3000.0
    range_noise_mm: float = 1.0                    # Gaussian range noise, 1 sigma
    range_noise_rel: float = 0.0                   # plus this fraction of the range (0.01: 1 %), 1 sigma
    beam_exit_mm: float = 1.5                      # footprint diameter (1/e^2) at the exit window
    beam_divergence_mrad: float = 1.5              # full-angle divergence (1/e^2)
    footprint_rings: int = 3                       # sub-ray rings across the footprint
    mixed_dominant: float = 0.85                   # energy share above which a surface wins alone
    detect_energy: float = 0.12                    # minimum returned energy for an echo
    lidar_offset_mm: tuple[Range, Range, Range] = ((-60.0, 60.0), (100.0, 200.0), (80.0, 180.0))
    lidar_misalign_deg: float = 3.0                # random roll / yaw of the LiDAR mount
    lidar_roll_deg: float = 0.0                    # mount roll about the LiDAR x axis (180: upside down)
    lidar_yaw_deg: float = 0.0                     # mount yaw: the V seen at beam angle -lidar_yaw_deg
    # --- turntable ---
    n_positions: int = 87
    psi_step_deg: float = 0.25
    psi0_deg: Range = (-25.0, 25.0)                # reported angle of the first position
    lever_arm_mm: Range = (20.0, 80.0)             # axis to LiDAR centre
    axis_tilt_deg: float = 3.0                     # axis direction from camera x
    # --- stripe rendering ---
    sheet_sigma_mm: Range = (0.5, 1.0)             # laser sheet 1-sigma half thickness at the board
    stripe_peak_dn: float = 235.0                  # white square, normal incidence, at the hinge range
    stripe_albedo_black: float = 0.32
    stripe_albedo_wall: float = 0.6
    ambient_dn: float = 0.0                        # white square in the dark frame (0: boards invisible)
    # --- image formation ---
    white_dn: float = 200.0                        # bright image, white square
    black_albedo: float = 0.18                     # bright image, black square / white
    wall_albedo: float = 0.3
    post_albedo: float = 0.25
    psf_sigma_px: float = 0.7
    bright_noise_dn: float = 1.0
    dark_level_dn: float = 2.0                     # black level of dark frames
    read_noise_dn: float = 0.25                    # 8-bit output of a 12-bit sensor: small
    shot_noise_gain: float = 0.03                  # variance per DN of signal
    supersample: int = 4                           # n x n samples on edge pixels
    # where those samples sit: "grid" (regular; an edge along the pixel rows or columns is
    # rendered up to 1/(2n) px off) or "multi-jittered" (n^2 distinct rows and columns;
    # render.subpixel_offsets)
    antialias: str = "grid"
    # --- nuisances (harsh) ---
    speckle_contrast: float = 0.0                  # std of log-intensity of the laser speckle
    speckle_corr_px: float = 1.5
    albedo_modulation: float = 0.0                 # std of a smooth log-albedo field on the stripe
    spurious_rate: float = 0.0                     # fraction of beams with a random range
    drop_rate: float = 0.0                         # fraction of beams with no return
    encoder_noise_deg: float = 0.0                 # reported psi = true psi + noise
    # --- LiDAR ranging errors (default off; lidar.py: apply_ranging_errors, dark_range_bias) ---
    range_offset_mm: float = 0.0                   # zero offset: every valid range reads this much too far
    dark_extra_mm: float = 0.0                     # returns from black squares read this much farther
    range_quantum_mm: float = 0.0                  # ranges rounded to multiples of this (0: none)
    incidence_extra_mm: float = 0.0                # sub-ray range + this * (1/cos(incidence) - 1)
    range_scale_error: float = 0.0                 # every valid range times (1 + this): a time-base error
    # --- disc measurement trials ---
    n_discs: int = 10
    disc_diameter_mm: float = 140.0
    disc_distance_mm: Range = (1400.0, 1600.0)
    disc_tilt_deg: float = 30.0
    disc_wall_gap_mm: Range = (500.0, 1000.0)
    disc_wall_size_mm: float = 1000.0              # square background panel behind the disc
    disc_beam_angle_deg: float = 20.0              # max |beam angle| of the disc centre
    sweep_step_deg: float = 0.05
    sweep_margin_deg: float = 0.4                  # extra psi before and after the disc
    # disc sizes: trial j has disc_diameters_mm[j % len] when given (else disc_diameter_mm)
    disc_diameters_mm: tuple[float, ...] = ()
    # --- footprint / echo model of the LiDAR (lidar.py): "gaussian" = Gaussian spot,
    # energy-weighted mixed echo; "first-echo" = uniform (top-hat) spot of the same diameter,
    # the nearest surface returning >= echo_threshold of the energy wins alone (no mixing) ---
    footprint_model: str = "gaussian"
    echo_threshold: float = 0.25
    # LiDAR reflectivities (relative energy) of the materials
    lidar_reflectivity: tuple[float, float, float, float] = (0.8, 0.5, 0.4, 0.7)  # board, wall, post, disc

    def disc_diameter(self, j: int) -> float:
        """Diameter (mm) of disc trial ``j``: ``disc_diameters_mm`` in turn, else ``disc_diameter_mm``."""
        if self.disc_diameters_mm:
            return float(self.disc_diameters_mm[j % len(self.disc_diameters_mm)])
        return float(self.disc_diameter_mm)

    def with_(self, **changes) -> RigConfig:
        """A copy with some fields changed (``dataclasses.replace``)."""
        return replace(self, **changes)


PAPER = RigConfig(
    name="paper",
    image_size=(1624, 1234),
    K=((2757.4, 0.0, 831.6), (0.0, 2758.6, 638.9), (0.0, 0.0, 1.0)),
    dist=(-0.076, 0.371, 0.0, 0.0, 0.0),
)

WIDE = RigConfig(
    name="wide",
    image_size=(1920, 1200),
    K=((1187.0, 0.0, 968.5), (0.0, 1189.5, 597.0), (0.0, 0.0, 1.0)),
    dist=(-0.30, 0.12, 0.0008, -0.0006, -0.02),
    camera_in_dataset=False,
    n_intrinsics_views=18,
    intrinsics_inner_corners=(9, 6),
    intrinsics_square_mm=30.0,
    intrinsics_fill=(0.3, 0.55),
    v_inner_corners=(7, 10),         # 10 x 7 inner corners, long side vertical
    v_square_mm=30.0,
    hinge_distance_mm=(760.0, 860.0),
    wall_distance_mm=(1800.0, 2600.0),
    lidar_angle_min_deg=-60.0,
    lidar_angle_max_deg=60.0,
    lidar_angle_step_deg=0.25,
    lidar_range_min_mm=100.0,
    lidar_range_max_mm=10000.0,
    range_noise_mm=2.0,
    beam_exit_mm=4.0,
    beam_divergence_mrad=3.0,
    lidar_offset_mm=((-80.0, 80.0), (100.0, 200.0), (0.0, 80.0)),
    n_positions=40,
    psi_step_deg=0.5,
    sheet_sigma_mm=(0.8, 1.4),
    disc_diameter_mm=200.0,
    disc_distance_mm=(1200.0, 1500.0),
    disc_beam_angle_deg=35.0,
    sweep_step_deg=0.1,
    ambient_dn=3.0,
    read_noise_dn=0.5,
    bright_noise_dn=1.5,
)

HARSH = PAPER.with_(
    name="harsh",
    speckle_contrast=0.45,
    speckle_corr_px=1.5,
    albedo_modulation=0.25,
    stripe_albedo_black=0.15,
    ambient_dn=25.0,
    read_noise_dn=3.0,
    bright_noise_dn=3.0,
    spurious_rate=0.01,
    drop_rate=0.02,
    encoder_noise_deg=0.003,
    beam_divergence_mrad=3.0,
    mixed_dominant=0.95,
)

FOOTPRINT_MODELS = ("gaussian", "first-echo")

RIGS: dict[str, RigConfig] = {"paper": PAPER, "wide": WIDE, "harsh": HARSH}


def get_rig(rig: str | RigConfig) -> RigConfig:
    """A preset by name, or the given config."""
    if isinstance(rig, RigConfig):
        return rig
    try:
        return RIGS[rig]
    except KeyError:
        raise ValueError(f"unknown rig {rig!r}; expected one of {sorted(RIGS)} or a RigConfig") from None
