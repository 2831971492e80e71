"""The filter core: state, covariance, the covariance prediction and the one measurement update.

The update is the Joseph form ``(I - K H) P (I - K H)' + K R K'`` of the gain actually used, which with the
partial-update (Schmidt) gain ``K = D K_opt`` (``D = diag(g)``) expands exactly to ``P - A o G`` with
``A = P H' S^-1 H P`` and ``G_ij = 1 - (1 - g_i)(1 - g_j)``: the optimal-gain update everywhere except the block of
the partial-update states, where ``A_ij (1 - g_i)(1 - g_j)`` is given back; the correction is ``D K_opt y``
(Brink's partial-update Schmidt-Kalman filter, JGCD 2017; 0 is a pure *consider* state, 1 the full update).
``A = L L'`` is formed from ``L = P H' C^-T`` (``S = C C'``, Cholesky in closed form for the scalar and 2-D
updates), so the update is two small products and a subtraction, and ``P`` stays symmetric to the last bit.
The NIS is gated against a named threshold.  Nothing is committed unless the update's factors are finite.  When an
innovation variance falls below its observation variance (``H P H' < 0``: ``P`` has lost positive definiteness) the
states the measurement touches get their initial covariance back and the measurement is skipped (PX4 EKF2).

The hot path runs about 150 updates per second, where every NumPy call costs 1-3 µs whatever its size, so the
count of calls is the cost: the small matrices are handled as Python floats.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from fusion.state import S
from fusion.status import REASON_COV_RESET, REASON_GATE, REASON_NUMERIC, StatusRow

log = logging.getLogger(__name__)

Vec = NDArray[np.float64]
Mat = NDArray[np.float64]

#: Relative tolerance of the covariance-health check: ``H P H'`` counts as negative (the PX4 condition "innovation
#: variance below observation variance") when a diagonal element is below ``-COV_RESET_REL_TOL * R``; smaller
#: negatives are rounding of an exactly zero variance (e.g. a clone taken this instant).
COV_RESET_REL_TOL = 1e-9


class Linearised(NamedTuple):
    """A measurement model at a state, in the form the update is cheapest with (diagonal ``R``).

    ``z_hat``: the prediction (m floats).  ``H``: the ``(n,)`` Jacobian row of a scalar measurement or the
    ``(m, n)`` Jacobian; ``None`` for a direct measurement of the states ``idx`` (``H`` = those rows of the
    identity, so ``P H'`` is a column selection).  ``r``: the diagonal of ``R`` (m floats)."""

    z_hat: tuple[float, ...]
    H: Vec | Mat | None
    idx: Sequence[int] | None
    r: Sequence[float]

    def columns(self) -> NDArray[np.intp]:
        """The states the measurement touches (those a covariance reset restores)."""
        if self.H is None:
            return np.array(self.idx)
        return np.flatnonzero(self.H if self.H.ndim == 1 else np.any(self.H != 0.0, axis=0))


def _chol_inv(Sm: list[list[float]]) -> list[list[float]] | None:
    """``C^-1`` (lower triangular, nested lists) of the Cholesky factor ``S = C C'`` of a small symmetric matrix;
    ``None`` if ``S`` is not positive definite.  Floats: for m <= 3 this is cheaper than NumPy's calls."""
    m = len(Sm)
    C = [[0.0] * m for _ in range(m)]
    for i in range(m):
        for j in range(i + 1):
            v = Sm[i][j] - sum(C[i][k] * C[j][k] for k in range(j))
            if i == j:
                if not v > 0.0:
                    return None
                C[i][i] = math.sqrt(v)
            else:
                C[i][j] = v / C[j][j]
    Ci = [[0.0] * m for _ in range(m)]
    for i in range(m):
        Ci[i][i] = 1.0 / C[i][i]
        for j in range(i):
            Ci[i][j] = -sum(C[i][k] * Ci[k][j] for k in range(j, i)) / C[i][i]
    return Ci


def _whiten(Sm: list[list[float]], y: Sequence[float]) -> tuple[Mat, list[float], float] | None:
    """``(C^-T, w = C^-1 y, w' w)`` of ``S = C C'`` (any small size); ``None`` unless ``S`` is positive definite."""
    Ci = _chol_inv(Sm)
    if Ci is None:
        return None
    w = [sum(Ci[i][k] * y[k] for k in range(i + 1)) for i in range(len(y))]
    return np.array(Ci).T, w, sum(v * v for v in w)


class FilterCore:
    """State ``x``, covariance ``P``, ``P = F P F' + Q`` and the one gated update (module docstring).

    ``init_var``: the initial variances, which a covariance reset restores.  ``on_reset`` callbacks get the indices
    of every reset (covariance or states) so the sources that hold derived state (the optical clone) drop it."""

    def __init__(self, x0: Vec, P0: Mat, init_var: Vec) -> None:
        self.x = x0
        self.P = P0
        self.init_var = init_var
        #: bumped at every change of ``x`` or ``P`` (outputs computed from them are cached per version)
        self.version = 0
        self.n_predictions = 0
        self.on_reset: list[Callable[[NDArray[np.intp]], None]] = []
        # partial-update (Schmidt) states: their rows of every gain are scaled down (module docstring)
        self._gain_scale = np.ones(S.dim)
        self._schmidt: list[tuple[int, int, float]] = []
        self._partial: list[tuple[int, float]] = []

    # ----------------------------------------------------------------------------------------------------------
    def predict(self, x_new: Vec, F: Mat, Q: Mat, add_var: Sequence[tuple[int, float]] = ()) -> None:
        """``x = x_new``, ``P = F P F' + Q`` symmetrised (``F P F'`` is symmetric only up to rounding), then the
        per-prediction variances ``add_var`` (index, variance) on the diagonal."""
        self.x = x_new
        FPF = F.dot(self.P).dot(F.T)
        FPF += Q
        P = FPF.T.copy()                 # (FPF' + FPF) / 2: the same sums as FPF + FPF', whose strided read of the
        P += FPF                         # transpose costs more than this contiguous copy and in-place add
        P *= 0.5
        for i, q in add_var:
            P[i, i] = P.item(i, i) + q
        self.P = P
        self.n_predictions += 1
        self.version += 1

    def partial_update_fraction(self, i: int) -> float:
        """The partial-update fraction of state ``i`` (1: full update)."""
        return float(self._gain_scale[i])

    def set_partial_update(self, i: int, fraction: float) -> None:
        """Partial-update (Schmidt) fraction of state ``i``: its row of every gain is multiplied by it."""
        self._gain_scale[i] = fraction
        part = [(int(k), 1.0 - float(self._gain_scale[k])) for k in np.flatnonzero(self._gain_scale != 1.0)]
        self._schmidt = [(a, b, ca * cb) for a, ca in part for b, cb in part]   # (i, j, (1 - g_i)(1 - g_j))
        self._partial = [(k, float(self._gain_scale[k])) for k, _ in part]      # (i, g_i) where g_i != 1

    # ----------------------------------------------------------------------------------------------------------
    def update(self, row: StatusRow, t_us: int, z: Sequence[float] | Vec, m: Linearised, gate_nis: float) -> bool:
        """Fuse the measurement ``z`` (model ``m`` at the current state) unless the numerics, the covariance-health
        check or the NIS gate say no; fills ``row`` and returns whether it was fused."""
        h = m.H
        if h is not None:
            if h.ndim == 1:
                return self._update_scalar(row, t_us, z[0] - m.z_hat[0], h, m, gate_nis)
            if len(m.z_hat) == 2:
                return self._update_2d(row, t_us, z, h, m, gate_nis)
        r = m.r
        PHt, hph_diag, Sm, innov = self._prior_terms(z, m)
        var = tuple([Sm[i][i] for i in range(len(innov))])     # (list comprehensions: no generator frames)
        if not math.isfinite(sum(innov) + sum(map(sum, Sm))):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC)
            return False
        if any([v < -COV_RESET_REL_TOL * ri for v, ri in zip(hph_diag, r, strict=True)]):
            self._cov_reset(row, t_us, m.columns(), innov, var)
            return False
        white = _whiten(Sm, innov)
        if white is None:
            row.set(t_us, rejected=True, reason=REASON_NUMERIC, innovation=innov, innovation_var=var)
            return False
        CiT, w, nis = white
        ratio = nis / gate_nis
        if not ratio <= 1.0:
            row.set(t_us, rejected=True, reason=REASON_GATE, innovation=innov, innovation_var=var, test_ratio=ratio)
            return False
        L = PHt.dot(CiT)                                  # L = P H' C^-T: L L' = P H' S^-1 H P; K_opt y = L C^-1 y
        check = float(np.vdot(L, L))                      # trace(A), whose finiteness is all that is asked
        return self._commit(row, t_us, L.dot(w), L.dot(L.T), check, innov, var, ratio)

    def _update_2d(self, row: StatusRow, t_us: int, z: Sequence[float] | Vec, H: Mat, m: Linearised,
                   gate_nis: float) -> bool:
        """:meth:`update` of a two-dimensional measurement with Jacobian ``H`` (2, n): the 2 x 2 algebra (``S``, its
        Cholesky factor ``C``, ``C^-1``, the whitened innovation) in closed form on floats."""
        r0, r1 = m.r
        zh0, zh1 = m.z_hat
        y0, y1 = z[0] - zh0, z[1] - zh1
        PHt = self.P.dot(H.T)
        (a, b), (c, d) = H.dot(PHt).tolist()
        s00, s01, s11 = a + r0, 0.5 * (b + c), d + r1
        innov, var = (y0, y1), (s00, s11)
        if not math.isfinite(y0 + y1 + s00 + s01 + s11):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC)
            return False
        if a < -COV_RESET_REL_TOL * r0 or d < -COV_RESET_REL_TOL * r1:
            self._cov_reset(row, t_us, m.columns(), innov, var)
            return False
        c00 = math.sqrt(s00) if s00 > 0.0 else 0.0     # C = [[c00, 0], [c10, c11]]
        c10 = s01 / c00 if c00 > 0.0 else 0.0
        c11_2 = s11 - c10 * c10                    # det(S) / s00: not positive (or its rounding) = not definite
        if not (c00 > 0.0 and c11_2 > 0.0):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC, innovation=innov, innovation_var=var)
            return False
        c11 = math.sqrt(c11_2)
        i00, i10, i11 = 1.0 / c00, -c10 / (c00 * c11), 1.0 / c11     # C^-1 = [[i00, 0], [i10, i11]]
        w0, w1 = i00 * y0, i10 * y0 + i11 * y1
        ratio = (w0 * w0 + w1 * w1) / gate_nis
        if not ratio <= 1.0:
            row.set(t_us, rejected=True, reason=REASON_GATE, innovation=innov, innovation_var=var, test_ratio=ratio)
            return False
        L = PHt.dot(np.fromiter((i00, i10, 0.0, i11), float, 4).reshape(2, 2))     # L = P H' C^-T
        return self._commit(row, t_us, L.dot(np.fromiter((w0, w1), float, 2)), L.dot(L.T), float(np.vdot(L, L)),
                            innov, var, ratio)

    def _update_scalar(self, row: StatusRow, t_us: int, y: float, h: Vec, m: Linearised, gate_nis: float) -> bool:
        """:meth:`update` of a scalar measurement (innovation ``y``, Jacobian row ``h``): floats throughout."""
        r = m.r[0]
        PHt = self.P.dot(h)
        hph = float(PHt.dot(h))
        s = hph + r
        if not (math.isfinite(y) and math.isfinite(s)):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC)
            return False
        if hph < -COV_RESET_REL_TOL * r:
            self._cov_reset(row, t_us, m.columns(), (y,), (s,))
            return False
        ratio = y * y / s / gate_nis
        if not ratio <= 1.0:
            row.set(t_us, rejected=True, reason=REASON_GATE, innovation=(y,), innovation_var=(s,), test_ratio=ratio)
            return False
        u = (PHt * (1.0 / math.sqrt(s))).reshape(-1, 1)  # u u' = P h' s^-1 h P; K_opt y = P h' y / s
        return self._commit(row, t_us, PHt * (y / s), u.dot(u.T), float(PHt.dot(PHt)), (y,), (s,), ratio)

    def _prior_terms(self, z: Sequence[float] | Vec, m: Linearised) -> tuple[Mat, list[float], list[list[float]],
                                                                          tuple[float, ...]]:
        """``P H'``, the diagonal of ``H P H'``, ``S`` (nested lists, symmetrised) and the innovation of a
        measurement of two or more dimensions."""
        P = self.P
        r = m.r
        if m.H is None:                                   # direct measurement: P H' is a column selection
            idx = list(m.idx or ())
            y = tuple((np.asarray(z) - self.x[idx]).tolist())
            PHt = P[:, idx]
            hph = PHt[idx].tolist()
        else:
            y = tuple(zi - zh for zi, zh in zip(z, m.z_hat, strict=True))
            PHt = P.dot(m.H.T)
            hph = m.H.dot(PHt).tolist()
        n = len(y)
        Sm = [[0.5 * (hph[i][j] + hph[j][i]) + (r[i] if i == j else 0.0) for j in range(n)] for i in range(n)]
        return PHt, [hph[i][i] for i in range(n)], Sm, y

    def _commit(self, row: StatusRow, t_us: int, dx: Vec, A: Mat, check: float, innov: tuple[float, ...],
                var: tuple[float, ...], ratio: float) -> bool:
        """Store ``x + D dx`` and ``P - A o G`` (the partial-update states' block given back) unless ``check`` (a
        sum of squares or products of every element of the update's factors, e.g. ``u @ u``) is non-finite; then
        the prior is kept.  A NaN or inf in a factor makes that sum non-finite, and with finite factors the update
        is finite: ``P`` is finite, and the NIS gate bounds ``|K y|`` by ``sqrt(gate * P_ii)`` and the subtracted
        term by ``|P_ij|``-sized values."""
        if not math.isfinite(check):
            row.set(t_us, rejected=True, reason=REASON_NUMERIC, innovation=innov, innovation_var=var,
                    test_ratio=ratio)
            return False
        P_new = self.P - A
        for i, g in self._partial:                 # D dx (element by element as Python floats: no NumPy scalars)
            dx[i] = dx.item(i) * g
        for i, j, cc in self._schmidt:             # partial-update states: P_ij += (1-g_i)(1-g_j) A_ij
            P_new[i, j] = P_new.item(i, j) + cc * A.item(i, j)
        self.x, self.P = self.x + dx, P_new
        self.version += 1
        row.fused_now(t_us, innov, var, ratio)
        return True

    # ----------------------------------------------------------------------------------------------------------
    def store(self, x: Vec, P: Mat) -> None:
        """Replace the state and covariance (resets, clones)."""
        self.x, self.P = x, P
        self.version += 1

    def _cov_reset(self, row: StatusRow, t_us: int, cols: NDArray[np.intp], innov: tuple[float, ...],
                   var: tuple[float, ...]) -> None:
        self.reset_covariance(cols)
        log.warning("EKF %s at %d us: innovation variance below observation variance, covariance of states %s reset",
                    row.source, t_us, cols.tolist())
        row.set(t_us, rejected=True, reason=REASON_COV_RESET, innovation=innov, innovation_var=var)

    def reset_covariance(self, idx: NDArray[np.intp]) -> None:
        """The states ``idx`` get their initial variance back, uncorrelated with the rest."""
        P = self.P.copy()
        P[idx, :] = 0.0
        P[:, idx] = 0.0
        P[idx, idx] = self.init_var[idx]
        self.store(self.x, P)
        for fn in self.on_reset:
            fn(idx)

    def reset_states(self, idx: NDArray[np.intp], z: Vec, R: Mat) -> None:
        """The states ``idx`` are set to ``z`` with covariance ``R``, uncorrelated with the rest."""
        x = self.x.copy()
        P = self.P.copy()
        x[idx] = z
        P[idx, :] = 0.0
        P[:, idx] = 0.0
        P[np.ix_(idx, idx)] = R
        self.store(x, P)
        for fn in self.on_reset:
            fn(idx)
