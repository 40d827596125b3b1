"""Parametrisation of the joint fit: constants, the linearisation point, rig and board poses."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..geometry import MAD_TO_SIGMA, median, plane_basis, unit

_CHI1_MEDIAN = 0.45493642311957283  # median of the chi-square distribution with 1 dof
N_RIG = 10  # axis direction 2, axis point 2, reference rotation 3, reference centre 3
N_BOARD = 6  # per board: rotation 3, translation 3
N_RANGING = 2  # range offset, dark-square extra (mm); the last entries of a parameter vector
F_SCALE = 2.5  # robust loss scale, in noise sigmas
CLIP_SIGMAS = 4.0  # residuals beyond this many sigmas do not enter the group moments
SIGNIFICANCE = 3.0  # a correlated-noise component enters when this many sigmas above zero
REJECT_SIGMAS = 5.0  # residuals beyond this many (whitened) sigmas are dropped after a first fit
CORNER_FLOOR_PX = 0.1  # chessboard corner accuracy assumed for the board planes' uncertainty
JITTER_LR = 25.0  # encoder jitter is modelled when its likelihood ratio exceeds this (~5 sigma)
MIN_POINTS_PER_BOARD = 8
# stripe offsets left after the jitter corrections, in the stripes' white noise, above which the
# jitter is not told apart from the offsets (measured: 14-18 on wide rigs with 0.02 deg
# jitter, poses' z axes up to 5 sigma off; 0.1 on the harsh preset's 0.003 deg, within 2 sigma)
JITTER_OFFSET_RATIO = 5.0
# a stripe or scan segment whose own white scale exceeds its board's by this factor keeps its
# own (joint.noise._Groups.own_scatter; measured by the MAD: combo r18's square-wave stripes
# 4-14x; the bundled paper rig's stripes median 1.01x, 90 % below 1.24x, 7 of 174 above 2x
# (their poses then moved 0.0002 mm), its scan segments at most 1.23x); at least this many rows
OWN_SCATTER_RATIO = 2.0
OWN_SCATTER_MIN_ROWS = 20
# central-difference steps: rotations / directions (rad), translations (mm)
_STEPS = np.array([1e-6] * 2 + [1e-3] * 2 + [1e-6] * 3 + [1e-3] * 3 + ([1e-6] * 3 + [1e-3] * 3) * 2)


@dataclass(frozen=True)
class _Base:
    """Linearisation point of the parametrisation."""

    k: np.ndarray
    B: np.ndarray  # (2, 3) basis perpendicular to k
    a: np.ndarray
    R: np.ndarray
    T: np.ndarray
    board_R: np.ndarray  # (2, 3, 3)
    board_T: np.ndarray  # (2, 3)
    ranging: np.ndarray  # (2,) range offset, dark-square extra (mm)

    @staticmethod
    def make(k, a, R, T, board_R, board_T, ranging=(0.0, 0.0)) -> _Base:
        k = unit(np.asarray(k, dtype=float))
        a = np.asarray(a, dtype=float)
        return _Base(k, plane_basis(k), a - (a @ k) * k, np.asarray(R, float), np.asarray(T, float),
                     np.asarray(board_R, float), np.asarray(board_T, float),
                     np.asarray(ranging, float).copy())


def _rig(x: np.ndarray, base: _Base):
    """(k, a, R_ref, T_ref) for rig parameters ``x[:10]``."""
    k = unit(base.k + x[0:2] @ base.B)
    a = base.a + x[2:4] @ base.B
    R = Rotation.from_rotvec(x[4:7]).as_matrix() @ base.R
    T = base.T + x[7:10]
    return k, a, R, T


def _boards(x: np.ndarray, base: _Base):
    """Board rotations (2, 3, 3) and translations (2, 3) for ``x[10:22]`` (zeros if absent)."""
    if len(x) <= N_RIG:
        return base.board_R, base.board_T
    xb = x[N_RIG:N_RIG + 2 * N_BOARD].reshape(2, N_BOARD)
    R = Rotation.from_rotvec(xb[:, :3]).as_matrix() @ base.board_R
    return R, base.board_T + xb[:, 3:]


def _poses(k, a, R_ref, T_ref, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rigid model at angles ``t`` (rad from psi_ref): R (N, 3, 3), T (N, 3).

    ``Q = cos t I + sin t [k]x + (1 - cos t) k k^T`` (Rodrigues, ``|k| = 1``)."""
    c, s = np.cos(t)[:, None, None], np.sin(t)[:, None, None]
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    Q = c * np.eye(3) + s * kx + (1 - c) * np.outer(k, k)
    return Q @ R_ref, a + (Q @ (T_ref - a)[:, None])[:, :, 0]



def _mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` for long inner dimensions without BLAS threads (einsum's C loop).

    Threaded BLAS on an oversubscribed machine turns these small products
    ((n, 1e5) x (1e5, n)) into seconds; the plain loop takes milliseconds.
    """
    return np.einsum("ik,kj->ij", A, B)


def _robust_sigma(r: np.ndarray, floor: float) -> float:
    """``MAD_TO_SIGMA x median |r|`` (the median absolute residual as a Gaussian sigma), at
    least ``floor``; 1 without residuals."""
    if len(r) == 0:
        return 1.0
    a = np.abs(r)  # a temporary: its median may reorder it (NaN: numpy's NaN median)
    med = float(np.median(a)) if np.isnan(a.max()) else median(a, overwrite=True)
    return float(max(MAD_TO_SIGMA * med, floor))
