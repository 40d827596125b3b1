"""Noise model of the joint fit: per-segment / per-stripe correlated errors (generalised least squares)."""

from __future__ import annotations

import numpy as np

from .params import (
    _CHI1_MEDIAN,
    CLIP_SIGMAS,
    MAD_TO_SIGMA,
    OWN_SCATTER_MIN_ROWS,
    OWN_SCATTER_RATIO,
    SIGNIFICANCE,
    _robust_sigma,
)

BLOCK_ROWS = 400  # groups this large on average are whitened group by group (cache-sized blocks)


class _Groups:
    """Noise model of one residual kind: per-(position, board) groups with correlated errors.

    Residual ``i`` of group ``g`` (one board's scan segment or stripe at one
    position) is ``e_i + b0_g + b1_g s_i``: white noise of sigma ``sigma[board]``
    plus a random offset and a random tilt along the segment (``s_i``: centred
    coordinate along it) with variances ``var0[board]``, ``var1[board]``. Stripe
    centres carry such errors (sub-pixel locking of the centre estimator varies
    slowly along a stripe and from one position to the next); ignoring them
    makes the covariance far too optimistic. ``whiten`` applies ``V^-1/2``
    (generalised least squares): with ``u0 = 1/sqrt(n)``, ``u1 = s/|s|``,
    ``V^-1/2 = (I - g0 u0 u0^T - g1 u1 u1^T) / sigma``,
    ``g_j = 1 - sqrt(sigma^2 / (sigma^2 + lambda_j))``, ``lambda0 = n var0``,
    ``lambda1 = |s|^2 var1``.
    """

    def __init__(self, pos: np.ndarray, board: np.ndarray, coords: np.ndarray, n_pos: int):
        self.gid = pos * 2 + board
        self.n_groups = 2 * n_pos
        self.board_of_group = np.arange(self.n_groups) % 2
        self.row_board = np.asarray(board)
        # residuals come grouped (position by position, board 0 then 1): group sums of a
        # whole Jacobian are then one np.add.reduceat instead of a bincount per column
        self._sorted = bool(np.all(self.gid[1:] >= self.gid[:-1]))
        self._size = np.bincount(self.gid, minlength=self.n_groups)  # rows per group
        self.n = self._size.astype(float)
        starts = np.searchsorted(self.gid, np.arange(self.n_groups))
        self._nonempty = np.flatnonzero(self.n > 0)
        self._starts = starts[self._nonempty]
        self.sc = _along(self, np.asarray(coords, float))
        # the grid layout (:meth:`pad`): row i of group g at g * n_max + its place in g
        self.n_max = int(self._size.max()) if self._sorted and len(self._size) else 0
        self._grid = None  # rows not grouped: no grid (the moment solver is not used)
        if self._sorted:
            first = np.repeat(np.cumsum(self._size) - self._size, self._size)
            self._grid = self.gid * self.n_max + (np.arange(len(self.gid)) - first)
        self.sigma = np.ones(2)
        self.var0 = np.zeros(2)
        self.var1 = np.zeros(2)
        self.var0_g = self.var1_g = self.sigma_g = None
        self.set_mask(np.ones(len(pos), bool))

    def set_mask(self, keep: np.ndarray) -> None:
        """Residuals that enter the fit (the group moments and the counts use only these)."""
        self.w = np.asarray(keep, float)
        self.n, self.ss = self._counts(self.w)
        self._update()

    def _counts(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per group: kept residuals ``n`` and ``|s|^2`` over them (weights ``w``)."""
        return self.group_sum(w), np.maximum(self.group_sum(w * self.sc**2), 1e-300)

    def set(self, sigma, var0, var1, var0_g=None, var1_g=None, sigma_g=None) -> None:
        """Noise components per board; ``var*_g`` and the white ``sigma_g`` optionally per
        group (robust weights)."""
        self.sigma = np.asarray(sigma, float)
        self.var0 = np.asarray(var0, float)
        self.var1 = np.asarray(var1, float)
        self.var0_g = None if var0_g is None else np.asarray(var0_g, float)
        self.var1_g = None if var1_g is None else np.asarray(var1_g, float)
        self.sigma_g = None if sigma_g is None else np.asarray(sigma_g, float)
        self._update()

    def _update(self) -> None:
        b = self.board_of_group
        s2 = self.sigma[b] ** 2 if self.sigma_g is None else self.sigma_g ** 2
        v0 = self.var0[b] if self.var0_g is None else self.var0_g
        v1 = self.var1[b] if self.var1_g is None else self.var1_g
        self.g0 = 1 - np.sqrt(s2 / (s2 + self.n * v0))
        self.g1 = 1 - np.sqrt(s2 / (s2 + self.ss * v1))
        self.sig_g = np.sqrt(s2)

    def moments(self, r: np.ndarray, w: np.ndarray | None = None, counts: tuple | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """Per-group mean and slope (least squares along ``s``) of ``r`` over the kept residuals
        (or weights ``w``; ``counts``: their :meth:`_counts`, when known)."""
        if w is None:
            w, n, ss = self.w, self.n, self.ss
        elif counts is not None:
            n, ss = counts
        else:
            n, ss = self._counts(w)
        wr = w * r
        return (self.group_sum(wr) / np.maximum(n, 1e-300),
                self.group_sum(wr * self.sc) / ss)

    def whiten(self, r: np.ndarray) -> np.ndarray:
        """``V^-1/2 r`` over the kept residuals (dropped ones do not enter the moments)."""
        if len(r) == 0:
            return r
        m0, m1 = self.moments(r)
        inv = 1 / self.sig_g
        return ((r * self.spread(inv) - self.spread(self.g0 * m0 * inv))
                - self.spread(self.g1 * m1 * inv) * self.sc)

    def whiten_columns(self, J: np.ndarray) -> np.ndarray:
        """:meth:`whiten` applied to every column of a Jacobian (the group terms spread back
        over their rows, :meth:`spread`)."""
        if J.shape[0] == 0:
            return J
        inv = 1 / self.sig_g
        blocked = self._sorted and len(J) >= BLOCK_ROWS * len(self._nonempty)
        if blocked:
            # large groups: one block of rows at a time (it stays in cache); both group sums
            # (of w J and of w s J) as one (2, n) x (n, k) product per group
            ws = np.stack([self.w, self.w * self.sc])
            sums = np.zeros((self.n_groups, 2, J.shape[1]))
            for g, a, b in zip(self._nonempty, self._starts, self._starts + self._size[self._nonempty]):
                np.matmul(ws[:, a:b], J[a:b], out=sums[g])
            a0 = sums[:, 0] * (self.g0 * inv / np.maximum(self.n, 1e-300))[:, None]
            a1 = sums[:, 1] * (self.g1 * inv / self.ss)[:, None]
        else:
            wJ = J * self.w[:, None]
            a0 = self.group_sums(wJ) * (self.g0 * inv / np.maximum(self.n, 1e-300))[:, None]
            np.multiply(wJ, self.sc[:, None], out=wJ)
            a1 = self.group_sums(wJ) * (self.g1 * inv / self.ss)[:, None]
        if blocked:
            out = np.empty_like(J)
            sc = self.sc
            for g, a, b in zip(self._nonempty, self._starts, self._starts + self._size[self._nonempty]):
                blk = np.multiply(J[a:b], inv[g], out=out[a:b])
                blk -= a0[g]
                blk -= sc[a:b, None] * a1[g]
            return out
        out = J * self.spread(inv)[:, None]
        out -= self.spread(a0)
        out -= self.spread(a1) * self.sc[:, None]
        return out

    def pad(self, v: np.ndarray) -> np.ndarray:
        """A value per row (M,) laid out group by group on a grid (G, n_max), zeros where a
        group has fewer rows (rows grouped, as built): per-group sums and products become
        one batched ``np.matmul`` over the groups (:func:`whiten_padded`)."""
        out = np.zeros(self.n_groups * self.n_max)
        out[self._grid] = v
        return out.reshape(self.n_groups, self.n_max)

    def pad_columns(self, A: np.ndarray) -> np.ndarray:
        """The columns of ``A`` (M, k) on the grid of :meth:`pad`, (G, k, n_max): a group's
        column is contiguous (long inner loops for numpy). Rows placed, then transposed."""
        k = A.shape[1]
        rows = np.zeros((self.n_groups * self.n_max, k))
        rows[self._grid] = A
        return np.ascontiguousarray(rows.reshape(self.n_groups, self.n_max, k).transpose(0, 2, 1))

    def unpad(self, A: np.ndarray) -> np.ndarray:
        """:meth:`pad` undone: the grid (G, n_max) back to rows (M,)."""
        return A.reshape(-1)[self._grid]

    def group_sums(self, A: np.ndarray) -> np.ndarray:
        """Per-group column sums of ``A`` (M, k) -> (G, k): one ``np.add.reduceat`` when the
        rows are grouped (position by position, board 0 then 1, as built), else a bincount
        per column."""
        out = np.zeros((self.n_groups, A.shape[1]))
        if not len(self._nonempty):
            return out
        if self._sorted:
            out[self._nonempty] = np.add.reduceat(A, self._starts, axis=0)
            return out
        for j in range(A.shape[1]):
            out[:, j] = np.bincount(self.gid, A[:, j], minlength=self.n_groups)
        return out

    def group_sum(self, v: np.ndarray) -> np.ndarray:
        """Per-group sum of a vector ``v`` (M,) -> (G,) (:meth:`group_sums` of one column)."""
        if not self._sorted:
            return np.bincount(self.gid, v, minlength=self.n_groups)
        out = np.zeros(self.n_groups)
        if len(self._nonempty):
            out[self._nonempty] = np.add.reduceat(v, self._starts)
        return out

    def spread(self, v: np.ndarray) -> np.ndarray:
        """Per-group values (G, ...) onto their rows (M, ...): ``np.repeat`` of grouped rows (a
        copy of contiguous blocks), else a gather by ``gid``."""
        if self._sorted:
            return np.repeat(v, self._size, axis=0)
        return v[self.gid]

    def estimate(self, r: np.ndarray, floor: float, components: bool = True) -> None:
        """Method-of-moments noise components from residuals ``r`` at a fit (see class doc).

        Residuals beyond ``CLIP_SIGMAS`` robust sigmas are left out. ``sigma``:
        1.4826 x median absolute within-group residual (group offset and tilt
        removed); ``var0 = mean(m0^2 - sigma^2 / n)``, ``var1 = mean(m1^2 -
        sigma^2 / |s|^2)`` over the board's groups, set only when significant
        (``SIGNIFICANCE`` standard errors above zero), else 0. Without ``components``:
        ``sigma`` only (white noise, the components 0).
        """
        if len(r) == 0:
            if not components:
                self.set(self.sigma, [0, 0], [0, 0])
            return
        sig, v0, v1 = np.ones(2), np.zeros(2), np.zeros(2)
        w = (np.abs(r) <= CLIP_SIGMAS * _robust_sigma(r, floor)).astype(float)
        m0, m1 = self.moments(r, w)
        within = r - self.spread(m0) - self.spread(m1) * self.sc
        for b in range(2):
            sel = self.row_board == b
            if not sel.any():
                continue
            sig[b] = _robust_sigma(within[sel & (w > 0)], floor)
        sig_g = self.own_scatter(within, self.w, sig)
        if not components:
            self.set(sig, v0, v1, sigma_g=sig_g)
            return
        w = (np.abs(within) <= CLIP_SIGMAS * sig[self.row_board]).astype(float)
        n, ss = self._counts(w)
        a0, a1 = self.moments(r, w, (n, ss))
        vg = [np.zeros(self.n_groups), np.zeros(self.n_groups)]
        sg = sig[self.board_of_group] if sig_g is None else sig_g
        for b in range(2):
            grp = (self.board_of_group == b) & (n >= 3)
            G = int(grp.sum())
            if G == 0:
                continue
            # a component is kept only when significant: without it, m^2 / var(m | white)
            # averages to 1 +- sqrt(2 / G) (chi-square, 1 dof, G groups)
            for v, a, nn, out in ((v0, a0, n, vg[0]), (v1, a1, ss, vg[1])):
                white = sg[grp] ** 2 / np.maximum(nn[grp], 1e-300)
                if np.mean(a[grp] ** 2 / white) > 1 + SIGNIFICANCE * np.sqrt(2.0 / G):
                    # typical level from the median (chi-square 1 dof: median 0.455), and a
                    # group with a larger effect keeps its own: heavy-tailed group errors
                    # (a stripe on an unlucky pixel phase) then cannot steer the fit
                    v[b] = max(float(np.median(a[grp] ** 2) / _CHI1_MEDIAN
                                     - np.median(white)), 0.0)
                    out[grp] = np.maximum(v[b], a[grp] ** 2 - white)
        self.set(sig, v0, v1, vg[0], vg[1], sig_g)

    def own_scatter(self, within: np.ndarray, w: np.ndarray, sig: np.ndarray) -> np.ndarray | None:
        """Per group, its own white scale where it exceeds ``OWN_SCATTER_RATIO`` times its
        board's ``sig`` (1.4826 x median absolute ``within`` residual over the group's kept
        rows, at least ``OWN_SCATTER_MIN_ROWS`` of them), else the board's; None when no group
        does (beyond the paper).

        A stripe whose centres scatter far more than the others' along it (blurred stripe
        and board images, the stripe near a square edge: a +-0.5 px square wave where the
        other stripes scatter 0.03 px; combo r18, poses' z axes 0.11 deg off at 2.6 sigma)
        then weighs as little as its scatter says instead of steering the fit; its scale also
        grows with its errors' correlation along it (lag-1 autocorrelation ``rho``:
        ``sqrt((1 + rho) / (1 - rho))``, the square wave's ~4x; the MAD alone left r18's z
        axes 0.11 deg off)."""
        own = sig[self.board_of_group].copy()
        keep = w > 0
        gid, a = self.gid[keep], np.abs(within[keep])
        order = np.lexsort((a, gid))
        gid, a = gid[order], a[order]
        n = np.bincount(gid, minlength=self.n_groups)
        start = np.cumsum(n) - n
        ok = n >= OWN_SCATTER_MIN_ROWS
        if not ok.any():
            return None
        lo, hi = start[ok] + (n[ok] - 1) // 2, start[ok] + n[ok] // 2
        mad = MAD_TO_SIGMA * 0.5 * (a[lo] + a[hi])  # each group's median of sorted |r|
        big = mad > OWN_SCATTER_RATIO * own[ok]
        if not big.any():
            return None
        idx = np.flatnonzero(ok)[big]
        for g, m in zip(idx, mad[big]):
            # rows along the stripe: correlated errors (a square wave) carry the information of
            # fewer rows; the scale grows by sqrt((1 + rho) / (1 - rho)) (lag-1 autocorrelation
            # rho, an AR(1) sequence's effective sample size)
            rows = np.flatnonzero(keep & (self.gid == g))
            e = within[rows[np.argsort(self.sc[rows])]]
            e = e - e.mean()
            rho = float(np.clip(np.sum(e[1:] * e[:-1]) / max(float(e @ e), 1e-300), 0.0, 0.98))
            own[g] = m * np.sqrt((1.0 + rho) / (1.0 - rho))
        return own


def _along(grp: _Groups, coords: np.ndarray) -> np.ndarray:
    """Centred coordinate of every point along its group's principal direction (the first
    right singular vector of the group's centred 2D coordinates; sign arbitrary); 0 in
    groups of fewer than 3 points.

    All groups at once: the principal direction is the leading eigenvector of each
    group's 2 x 2 scatter matrix.
    """
    if len(coords) == 0:
        return np.zeros(0)
    n = grp._size
    mean = grp.group_sums(coords) / np.maximum(n, 1)[:, None]
    q = coords - grp.spread(mean)
    qx, qy = q[:, 0], q[:, 1]
    sxx, sxy, syy = grp.group_sum(qx * qx), grp.group_sum(qx * qy), grp.group_sum(qy * qy)
    _, V = np.linalg.eigh(np.stack([np.stack([sxx, sxy], 1), np.stack([sxy, syy], 1)], 1))
    v = V[:, :, 1] * (n >= 3)[:, None]  # eigenvalues ascending: the last is the principal direction
    return np.einsum("ij,ij->i", q, grp.spread(v))


def _blocked(grp: _Groups, h: np.ndarray) -> bool:
    """Whether the rows of ``h`` go group by group (:data:`BLOCK_ROWS`)."""
    return grp._sorted and len(h) >= BLOCK_ROWS * max(len(grp._nonempty), 1)


def _blocks(grp: _Groups):
    """(group, first row, end row) of every non-empty group (rows grouped)."""
    return zip(grp._nonempty, grp._starts, grp._starts + grp._size[grp._nonempty])


def _rows_dot(h: np.ndarray, c: np.ndarray, grp: _Groups) -> np.ndarray:
    """``h_i . c_g`` of every row ``i`` with its group's coefficients: ``c`` (G, k) gives (M,),
    ``c`` (G, k, q) gives (M, q) (row ``i`` times its group's matrix)."""
    if not _blocked(grp, h):
        if c.ndim == 2:
            return np.einsum("mk,mk->m", h, grp.spread(c))
        return np.einsum("mk,mkq->mq", h, grp.spread(c))
    r = np.zeros((len(h),) + c.shape[2:])
    for g, i, j in _blocks(grp):
        np.dot(h[i:j], c[g], out=r[i:j])
    return r


def whiten_padded(grp: _Groups, h: np.ndarray) -> np.ndarray:
    """:meth:`_Groups.whiten_columns` times the mask ``w`` of observations on the grid of
    :meth:`_Groups.pad_columns`, ``h`` (G, k, n_max), in place: ``(h - g0 m0 - g1 s m1) w /
    sigma`` with the group means ``m0 = sum w h / n`` and slopes ``m1 = sum w s h / |s|^2``
    as one batched product over the groups (padding has ``w = 0``: it stays zero)."""
    inv = 1 / grp.sig_g
    out, w = h, grp.pad(grp.w)
    if not (np.any(grp.g0) or np.any(grp.g1)):  # white noise (no group terms): a scaling
        out *= inv[:, None, None]
        out *= w[:, None, :]
        return out
    s = grp.pad(grp.sc)
    sums = np.matmul(out, np.stack([w, w * s], 2))  # (G, k, 2)
    a0 = sums[:, :, 0] * (grp.g0 * inv / np.maximum(grp.n, 1e-300))[:, None]
    a1 = sums[:, :, 1] * (grp.g1 * inv / grp.ss)[:, None]
    out *= inv[:, None, None]
    out -= a0[:, :, None]
    out -= a1[:, :, None] * s[:, None, :]
    out *= w[:, None, :]
    return out


def padded_rows_dot(grp: _Groups, h: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``h_i . c_g`` of every row with its group's coefficients ``c`` (G, k), ``h`` on the grid
    of :meth:`_Groups.pad_columns` (G, k, n_max): rows (M,)."""
    return grp.unpad(np.matmul(c[:, None, :], h))
