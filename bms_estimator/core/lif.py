"""Linear integral filter (LIF) regressors, batch and streaming.

The LIF turns the 2-RC ODE::

    v_o'' = th1 v_o' + th2 v_o + th3 i'' + th4 i' + th5 i + th6

into an algebraic regression without differentiating noisy signals.  Over a
window of L samples (step Ts, T = L Ts)::

    f1 = 1 - q^-L                                  (difference over the window)
    f2 = Ts (0.5 + q^-1 + ... + q^-(L-1) + 0.5 q^-L)   (trapezoidal integral)

Applying f2^2 to the ODE (f2 d/dt = f1 for sampled signals, exact for piecewise
linear signals)::

    f1^2 v_o = th1 f1 f2 v_o + th2 f2^2 v_o + th3 f1^2 i + th4 f1 f2 i + th5 f2^2 i + th6 T^2

i.e. ``y = phi' theta + e`` with ``y = f1^2 v_o`` and
``phi = [f1f2 v_o, f2^2 v_o, f1^2 i, f1f2 i, f2^2 i, T^2]``.

Scaling.  The raw regressors span many decades (``f2^2`` grows as T^2, current
as the cell size), so a fixed RLS tuning would depend on L and on the cell.
We regress on ``phi_s = phi / scale`` and ``theta_s = theta * scale`` with::

    scale = [T, T^2, I_ref, T I_ref, T^2 I_ref, T^2]

(``I_ref`` = 1C in ampere), which makes every column O(volt) for every window
and every cell size; ``phi_s' theta_s == phi' theta`` exactly.

Each of f1^2, f1 f2, f2^2 is an FIR filter of length 2L+1; the streaming
version keeps a ring buffer of the last 2L+1 samples per cell and evaluates the
three filters as one matrix product (slots x cells, so that a new sample is
one contiguous row), so it is exact (no running-sum drift) and
bit-for-bit reproducible against the batch version up to summation order.

Extra inputs.  A model with further known inputs u_m (functions of the
current, say a kinetic term; see :mod:`bms_estimator.core.lif_bv`) adds, per
input, the three columns ``[f1^2 u_m, f1f2 u_m, f2^2 u_m]`` after the six
above, scaled like the current's (``[I_ref, T I_ref, T^2 I_ref]``).
"""

from __future__ import annotations

import numpy as np
from scipy.signal import lfilter

from .cells import cell_vector

__all__ = ["lif_kernels", "lif_scale", "lif_regressors", "LifHistory"]


def lif_kernels(window: int, dt_s: float) -> np.ndarray:
    """FIR kernels, shape (2L+1, 3): columns f1^2, f1 f2, f2^2; row j = coefficient of q^-j."""
    if window < 1:
        raise ValueError(f"LIF window must be >= 1 sample, got {window}")
    f1 = np.zeros(window + 1)
    f1[0], f1[-1] = 1.0, -1.0
    f2 = np.full(window + 1, dt_s)
    f2[0] = f2[-1] = 0.5 * dt_s
    return np.stack([np.convolve(f1, f1), np.convolve(f1, f2), np.convolve(f2, f2)], axis=1)


def lif_scale(window: int, dt_s: float, i_ref_a: float, extra_inputs: int = 0) -> np.ndarray:
    """Column scale of the regressor (see module docstring): theta_s = theta * scale."""
    t = window * dt_s
    current = [i_ref_a, t * i_ref_a, t * t * i_ref_a]
    return np.array([t, t * t, *current, t * t] + current * extra_inputs)


def lif_regressors(
    v_o: np.ndarray, current_a: np.ndarray, window: int, dt_s: float, i_ref_a: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Batch LIF regression data.

    Args:
        v_o: overpotential v - OCV(soc), shape (n,) or (n, N).
        current_a: current, same shape.
    Returns:
        ``(y, phi_s)`` with shapes ``v_o.shape`` and ``v_o.shape + (6,)``, scaled as
        described in the module docstring.  The first 2L samples see the filter's
        zero initial state and should be discarded.
    """
    k = lif_kernels(window, dt_s)
    v = np.asarray(v_o, dtype=float)
    i = np.asarray(current_a, dtype=float)
    fv = [lfilter(k[:, c], [1.0], v, axis=0) for c in range(3)]
    fi = [lfilter(k[:, c], [1.0], i, axis=0) for c in range(3)]
    t2 = (window * dt_s) ** 2
    phi = np.stack([fv[1], fv[2], fi[0], fi[1], fi[2], np.full_like(v, t2)], axis=-1)
    return fv[0], phi / lif_scale(window, dt_s, i_ref_a)


class LifHistory:
    """Streaming LIF regressors for N cells sampled together.

    ``push(v_o, i)`` appends one sample per cell and returns ``(y, phi_s)`` of
    shapes (N,) and (N, 6).  ``shift_v_o(dv)`` subtracts a per-cell constant from
    the stored overpotential history (used when an OCV bias is moved into the SOC).

    With ``aux=True`` a third signal x (an auxiliary model's simulated v_o) is
    filtered alongside: ``push(v_o, i, x)``, and :meth:`instruments` then gives
    phi_s with its two v_o columns taken from x (the recursive IV's instrument).

    With ``extra_inputs=m`` the model has m further inputs besides the current:
    ``push(v_o, i, x, extra)`` with ``extra`` of shape (m, N), and phi_s gains
    3 m columns (module docstring).
    """

    def __init__(self, n_cells: int, window: int, dt_s: float, i_ref_a: float = 1.0, aux: bool = False,
                 extra_inputs: int = 0):
        self.n_cells = int(n_cells)
        self.window = int(window)
        self.dt_s = float(dt_s)
        self.length = 2 * self.window + 1
        k = lif_kernels(self.window, self.dt_s)
        # rolled[h, pos, c]: kernel coefficient for buffer slot pos when the newest sample is at h
        lags = (np.arange(self.length)[:, None] - np.arange(self.length)[None, :]) % self.length
        self._rolled = np.ascontiguousarray(k[lags].transpose(0, 2, 1))  # (h, 3, pos)
        self.extra_inputs = int(extra_inputs)
        self._scale = lif_scale(self.window, self.dt_s, i_ref_a, self.extra_inputs)
        self._inv_scale = 1.0 / self._scale
        self._t2_s = (self.window * self.dt_s) ** 2 * self._inv_scale[5]
        # [v_o, i(, x), u_1..u_m] x slots x cells: a new sample is one contiguous row per signal
        self._aux = bool(aux)
        self._buf = np.zeros((2 + self._aux + self.extra_inputs, self.length, self.n_cells))
        self._fx = np.zeros((self.n_cells, 3))
        self.head = -1
        self.count = 0
        self._groups: list[slice] | None = None  # see set_groups
        self._gbuf: np.ndarray | None = None  # equal groups: the ring buffer group-major, (group, signal, slot, cell)

    def set_groups(self, sizes) -> None:
        """Cells in consecutive groups of ``sizes`` (independent packs side by side): the filter
        product is then taken group by group, each with its own group's width. (BLAS picks its
        kernels by the matrix width, and for narrow ones a cell's result moves in the last bit
        with the width: per group, each group's filtered values are those it has alone.)"""
        if self._gbuf is not None:  # grouped before: back to the shared layout first
            self._buf = np.ascontiguousarray(self.buffer.transpose(0, 2, 1))
            self._gbuf = None
        bounds = np.concatenate(([0], np.cumsum(np.asarray(sizes, dtype=np.int64))))
        if bounds[-1] != self.n_cells or np.any(np.diff(bounds) < 1):
            raise ValueError(f"groups of {np.diff(bounds).tolist()} cells do not make the {self.n_cells} cells")
        self._groups = [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:])]
        sizes = np.diff(bounds)
        if sizes.size > 1 and (sizes == sizes[0]).all():
            # groups of equal size (the batch's stack): each group's history contiguous, so the product
            # reads it in place instead of copying it out of the shared buffer on every push
            self._gbuf = self._group_major(self._buf)
            self._buf = None

    def _group_major(self, buf: np.ndarray) -> np.ndarray:
        """(signal, slot, cell) -> contiguous (group, signal, slot, cell of the group); equal groups."""
        g = len(self._groups)
        return np.ascontiguousarray(buf.reshape(buf.shape[0], buf.shape[1], g, -1).transpose(2, 0, 1, 3))

    def _by_group(self, x, rows: int | None = None) -> np.ndarray:
        """A per-cell vector (or ``rows`` of them) as (group, [rows,] cell of the group)."""
        g = len(self._groups)
        if rows is None:
            return cell_vector(x, self.n_cells).reshape(g, -1)  # (a view of x when it is an (N,) float vector)
        return np.broadcast_to(np.asarray(x, dtype=float), (rows, self.n_cells)).reshape(rows, g, -1).transpose(1, 0, 2)

    @property
    def scale(self) -> np.ndarray:
        return self._scale

    @property
    def ready(self) -> bool:
        """True once the window holds 2L+1 real samples."""
        return self.count >= self.length

    def push(self, v_o: np.ndarray, current_a: np.ndarray, aux: np.ndarray | None = None,
             extra: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        self.head = (self.head + 1) % self.length
        if self._gbuf is not None:
            return self._push_group_major(v_o, current_a, aux, extra)
        buf = self._buf
        buf[0, self.head] = v_o
        buf[1, self.head] = current_a
        if aux is not None:
            buf[2, self.head] = aux
        if self.extra_inputs:
            buf[2 + self._aux:, self.head] = extra
        self.count += 1
        if self._groups is None:
            f = self._rolled[self.head] @ buf  # (signals, 3, N)
        else:
            k = self._rolled[self.head]
            f = np.concatenate([k @ np.ascontiguousarray(buf[:, :, g]) for g in self._groups], axis=2)
        return self._regressors(f)

    def _push_group_major(self, v_o, current_a, aux, extra) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`push` on the group-major buffer: the same products, on the same values, without copies."""
        gbuf = self._gbuf
        gbuf[:, 0, self.head] = self._by_group(v_o)
        gbuf[:, 1, self.head] = self._by_group(current_a)
        if aux is not None:
            gbuf[:, 2, self.head] = self._by_group(aux)
        if self.extra_inputs:
            gbuf[:, 2 + self._aux:, self.head] = self._by_group(extra, self.extra_inputs)
        self.count += 1
        k = self._rolled[self.head]
        return self._regressors(np.concatenate([k @ gbuf[g] for g in range(gbuf.shape[0])], axis=2))

    def _regressors(self, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(filtered v_o, phi_s) from the filter products ``f`` (signals, 3, N)."""
        if self._aux:
            self._fx = f[2].T
        fv, fi = f[0], f[1]
        phi = np.empty((len(self._scale), self.n_cells))
        phi[0] = fv[1]
        phi[1] = fv[2]
        phi[2:5] = fi
        phi[5] = self._t2_s
        if self.extra_inputs:
            phi[6:] = f[2 + self._aux:].reshape(3 * self.extra_inputs, self.n_cells)
            phi[6:] *= self._inv_scale[6:, None]
        phi[:5] *= self._inv_scale[:5, None]
        return fv[0], phi.T

    def instruments(self, phi: np.ndarray) -> np.ndarray:
        """phi_s of the last push with its v_o columns replaced by those of the auxiliary signal."""
        zeta = phi.copy()
        zeta[:, 0] = self._fx[:, 1] * self._inv_scale[0]
        zeta[:, 1] = self._fx[:, 2] * self._inv_scale[1]
        return zeta

    def shift_v_o(self, dv: np.ndarray) -> None:
        """Subtract dv from the stored v_o (and auxiliary-model) history."""
        d = np.asarray(dv, dtype=float)
        if self._gbuf is not None:
            if d.ndim == 0 or d.shape == (self.n_cells,):
                d = self._by_group(d)[:, None, :]  # (group, slot, cell): the same element-wise subtraction
                self._gbuf[:, 0] -= d
                if self._aux:
                    self._gbuf[:, 2] -= d
                return
            buf = self.buffer.transpose(0, 2, 1).copy()
            buf[0] -= d
            if self._aux:
                buf[2] -= d
            self._gbuf = self._group_major(buf)
            return
        self._buf[0] -= d
        if self._aux:
            self._buf[2] -= d

    @property
    def buffer(self) -> np.ndarray:
        """The ring buffer as (signal, cell, slot) (a view; a copy with equal groups)."""
        if self._gbuf is not None:
            g = self._gbuf
            return g.transpose(1, 0, 3, 2).reshape(g.shape[1], self.n_cells, self.length)
        return self._buf.transpose(0, 2, 1)

    def state_dict(self) -> dict[str, np.ndarray]:
        return {"buffer": self.buffer.copy(), "head": np.array(self.head), "count": np.array(self.count)}

    def load_state_dict(self, state: dict[str, np.ndarray]) -> None:
        buf = np.asarray(state["buffer"], dtype=float)
        if buf.shape != self.buffer.shape:
            raise ValueError(f"LIF history shape {buf.shape} does not match {self.buffer.shape}")
        self._buf = np.ascontiguousarray(buf.transpose(0, 2, 1))
        if self._gbuf is not None:
            self._gbuf = self._group_major(self._buf)
            self._buf = None
        self.head = int(state["head"])
        self.count = int(state["count"])
