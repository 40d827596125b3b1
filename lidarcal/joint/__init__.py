"""Joint fit of the whole rig to every stripe pixel and every scan point (beyond the paper).

The paper solves each turntable position alone (section 1) and then fits
functions of psi to those samples (section 2): every step throws information
away. Here the rigid turntable model of :class:`lidarcal.turntable.RigidModel`,
``pose(psi) = Rot(axis, psi - psi_ref) o pose_ref``, is fitted directly to the
raw observations of all positions at once by robust least squares
(maximum likelihood under the noise model below), started from the rigid
model and the paper's chain (the lower robust cost wins; costs within the start
solves' tolerance tie and the first start is kept, and the second stops as soon as
it is within one sigma of the first's solution); the covariance of
the result comes from the Jacobian at the solution.

Unknowns (minimal parametrisation, 10 + optionally 12):
axis direction ``k`` (2: a step in the plane perpendicular to the start
direction, then normalised), axis point ``a`` (2: a step perpendicular to
``k``; the position along the axis is a gauge), the LiDAR pose at the
reference angle (rotation vector 3 and centre 3); with ``fit_planes`` the two board poses (3 + 3 each);
with ``ranging`` (default) the LiDAR's range offset
and, when the returns from black squares can be told, their extra range
(:mod:`lidarcal.ranging`; a prior from dataset.json or a wide default enters as
one more observation each; the rig covariance is marginal over them).

Residuals:

* scan: every kept board return ``p`` of every scan (eq. 6, LiDAR frame; its range
  corrected by the ranging model) against its board's plane:
  ``n_b . (R(psi) p + T(psi)) - d_b`` (mm, eq. 3 and eq. 28);
* stripe: every stripe-centre pixel, back-projected onto its board's plane
  (eq. 5), against the laser plane the model predicts at that psi (the LiDAR's
  z = 0 plane): the distance in mm times the local image scale (pixels of
  stripe displacement, perpendicular to the imaged stripe, per mm of laser-
  plane offset, through the lens model), i.e. the pixel distance from the
  centre to the predicted stripe curve. The scale goes as 1 / depth of the board
  point, so the residual stays in pixels when the planes move: scaling planes and
  LiDAR about the camera centre leaves the image, and every stripe residual, as it
  is (a scale held at the start planes would let the fit shrink the scene toward the
  camera to shrink the stripe residuals);
* corners (only with ``fit_planes``): reprojection of the chessboard corners
  of both boards through the lens model (pixels); or instead, with
  ``plane_prior``, the camera's board poses as a Gaussian prior with their full
  covariance (corners floored at ``CORNER_FLOOR_PX``, plus the intrinsics'
  uncertainty when the camera was calibrated from photos,
  :mod:`lidarcal.joint.planes_prior`).

Board planes: one image (``board.png``) gives them; on a wide rig (few pixels per
mm, camera calibrated from photos) they limit the pose function, and the scans and
stripes of all positions correct them (rendered wide rigs, seeds 37, 39, 1, 5, 7, 40
positions: pose function's mean centre error 0.17 / 0.29 / 0.13 / 0.27 / 0.36 mm held
-> 0.15 / 0.19 / 0.13 / 0.28 / 0.32 mm fitted); on the paper and harsh rigs the change
is within the spread (bundled 0.086 -> 0.092, seed 11 0.097 -> 0.096, harsh 61
0.042 -> 0.033 mm). With the sharper board.png corners and a camera fitted with the
V's boards (:func:`lidarcal.board.sharpest_corners`, :func:`lidarcal.camera.add_views`)
the planes from the camera are better and the gain is smaller: held -> fitted 0.075 /
0.121 / 0.140 / 0.233 / 0.365 -> 0.080 / 0.113 / 0.100 / 0.223 / 0.363 mm on seeds 1,
37, 39, 5, 7. The row-wise solver it needs costs about ten times the held fit's, so
the planes are held by default (``lidarcal calibrate --fit-planes`` frees
them). The fit then checks how far it moved the planes (chi-square of the
shift under the camera's floored covariance, 12 dof) and warns beyond its 99.9 % point.
``plane_prior`` lets the data move the planes further (looser, floored covariance):
better with an exact camera on the wide rig (0.11 -> 0.09 mm) but, with a camera from
photos, the scans' and stripes' own systematic errors then move the planes
(0.15 -> 0.46 mm on wide seed 37): it is not the default.

Noise model (every scale estimated from the data, never a constant): per board,
white noise (1.4826 x median absolute residual) plus, per scan segment and
per stripe, a random offset and a random tilt (:class:`_Groups`, generalised
least squares; entered only when significant). Stripe centres from real
images carry such correlated errors (measured on rendered data: lag-1
autocorrelation ~0.4, per-stripe mean errors 3-6x the white prediction);
without them the covariance is far too optimistic. After a first robust fit
(``loss``, residuals in sigmas, scale ``F_SCALE``) the noise is re-estimated
and residuals beyond ``REJECT_SIGMAS`` are dropped (a bounded loss still
pulls with constant force per outlier), twice.

Encoder jitter (:func:`angle_jitter`): a turntable whose encoder reports each
angle with a random error turns all of a position's observations together. With
the rig held, each position's own angle step is estimated from its residuals;
the jitter variance maximises the steps' marginal likelihood (random effects);
when the data show a jitter (likelihood ratio above ``JITTER_LR``) every
position's angle gets its posterior correction, the noise is re-estimated and
the rig refitted. ``poses`` are then the function at the corrected angles, and
their sigmas include each angle's remaining uncertainty. Without jitter nothing
changes.

The segment <-> board assignment of each position is the one the single-shot
solution chose (``pose.info["pairs"]``: camera board ``k`` <-> scan segment
``pairs[k]``).

Covariance: ``s^2 (J^T W J)^-1`` with ``W`` the robust loss's IRLS weights (1 for
prior pseudo-observations) and ``s^2 >= 1`` the weighted residual variance; with
``fit_planes`` the corner rows' information assumes at least ``CORNER_FLOOR_PX``
per coordinate. With ``fit_planes=False`` the
board planes are held (default: the ``cv2.solvePnP`` poses, the corners' ML
estimate); their uncertainty is propagated into the rig parameters as a
"consider" covariance, ``A P A^T`` with ``A = (J_x^T J_x)^-1 J_x^T J_b``. Corner
errors of chessboard detectors are correlated over the board, so the
reprojection residuals understate the plane error; the planes' information
assumes at least ``CORNER_FLOOR_PX`` per corner coordinate. A camera given in
dataset.json is taken as exact; a camera calibrated from photos adds its intrinsics'
uncertainty carried through the PnP board poses (``P`` of :mod:`lidarcal.joint.planes_prior`
used as the held planes' covariance): the intrinsics' error turns both planes, so the
whole rig, coherently (paper camera from 12 photos, 14 positions: z-axis error 0.0034 deg
was outside 2-sigma 0.0014 at every position, now inside; a conservative bound, the
stripe rays held).

Solver (planes held): :func:`lidarcal.joint.moments.irls_moments`.
Every residual is linear in a short homogeneous vector of its observation with
coefficients that depend on the parameters per (position, board) only, and the
correlated-noise whitening is linear too: with the robust weights held, a
group's weighted sum of squares is exactly ``c^T Q c`` with its second-moment
matrix ``Q``, so an iteration costs O(positions); the weights are updated
between inner solves, whose model is the robust cost's second-order one (Newton
passes; the IRLS pass as fallback). The derivatives of ``c`` wrt the rig
parameters are analytic (:func:`lidarcal.joint.problem.pose_jacobian`); the
covariance above and the jitter test's angle steps come from the same moments
(exact). ``solver="lm"``: :func:`irls_lm`, the same
optimum row by row (Levenberg-Marquardt on the (n, n) normal equations,
weights updated every iteration; used with ``fit_planes``);
``solver="scipy"``: ``scipy.optimize.least_squares`` (dense SVD of the ~1e5 x n
Jacobian each iteration, slow).

Convention: as :mod:`lidarcal.turntable` (increasing psi turns right-handedly
about ``axis.direction``); mm and degrees at the edges, radians inside.
"""

from .data import JointData, build_joint_data, joint_data
from .fit import fit_joint, fit_joint_data, joint_warnings
from .jitter import angle_jitter
from .model import JointModel
from .params import (
    CLIP_SIGMAS,
    CORNER_FLOOR_PX,
    F_SCALE,
    JITTER_LR,
    MAD_TO_SIGMA,
    MIN_POINTS_PER_BOARD,
    N_BOARD,
    N_RIG,
    REJECT_SIGMAS,
    SIGNIFICANCE,
)
from .solver import LMResult, irls_lm

__all__ = ["CLIP_SIGMAS", "CORNER_FLOOR_PX", "F_SCALE", "JITTER_LR", "MAD_TO_SIGMA",
           "MIN_POINTS_PER_BOARD", "N_BOARD", "N_RIG", "REJECT_SIGMAS", "SIGNIFICANCE", "JointData",
           "JointModel", "LMResult", "angle_jitter", "build_joint_data", "fit_joint",
           "fit_joint_data", "irls_lm", "joint_data", "joint_warnings"]
