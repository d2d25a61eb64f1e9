"""Weighted recursive least squares for N independent regressions at once.

For each cell, with regressor phi_t (p,), measurement y_t, forgetting factor
lambda and weight w_t in {0, 1} (turn-on/turn-off adaptation)::

    e_t     = y_t - phi_t' theta_{t-1}                        (a-priori error)
    k_t     = P_{t-1} phi_t / (lambda + phi_t' P_{t-1} phi_t)
    theta_t = theta_{t-1} + w_t k_t e_t
    P_t     = (P_{t-1} - w_t k_t phi_t' P_{t-1}) / lambda^{w_t}

Adaptation is switched by the RMS of e over the last ``error_window`` samples:
on when it exceeds ``error_on``, off when it falls below ``error_off``
(hysteresis between the two).  While off, neither theta nor P moves, so P
cannot wind up during weakly exciting stretches (rest, constant current).

Covariance limit: when trace(P) exceeds ``trace_max`` P is scaled down to it,
which bounds the gain after long poorly exciting periods.

Initialisation (block least squares): the first ``init_samples`` regressors of
each cell are accumulated with forgetting, ``R = sum lambda^(n-k) phi phi'``
and ``r = sum lambda^(n-k) phi y``; then ``P0 = (R + delta)^-1`` and
``theta0 = P0 (r + delta theta_ref)``.  This is the RLS solution from a diffuse
start, but without its transient.  The small ridge ``delta`` (relative to each
column's energy, diag(R)) keeps P0 finite; in directions the block does not
excite it leaves theta0 at ``theta_ref`` (a prior the caller sets, zero by
default) rather than at 0.

Stabilised forgetting (``prior_share`` > 0; off by default).  Exponential
forgetting discounts the old information in every direction, also in those the
new data do not renew: there P^-1 decays towards 0 and theta drifts freely (two
nearly collinear columns, e.g. c0 and a slow RC branch under a steady current,
move together).  Kulhavy and Zarrop's regularised forgetting (Int. J. Control
58, 1993) forgets toward a prior theta_ref ~ N(theta_ref, Pi) instead::

    P_t^-1          = lambda P_{t-1}^-1 + (1 - lambda) Pi^-1 + w_t phi_t phi_t'
    P_t^-1 theta_t  = lambda P_{t-1}^-1 theta_{t-1} + (1 - lambda) Pi^-1 theta_ref + w_t phi_t y_t

(the recursive IV's instrument zeta in place of phi: :mod:`~bms_estimator.core.riv`),
so with no data the information settles at Pi^-1 and theta at theta_ref, and
with data every direction keeps at least the prior's information.  The prior
term is added every ``prior_every`` (M) learning samples of a cell, as the M
steps' sum ``a = (1 - lambda^M) Pi^-1`` (exact for the forgetting alone)::

    P     <- (P^-1 + A)^-1 = (I + P A)^-1 P            A = diag(a)
    theta <- theta + (I + P A)^-1 P A (theta_ref - theta)

(a Kalman update with the pseudo-measurement theta = theta_ref of covariance
A^-1; no inverse of P).  Pi is diagonal and set per cell from its block start:
``Pi^-1 = prior_share / (1 - lambda) diag(e)``, with e_j the block's mean
(forgetting-weighted) energy of column j, floored like the block ridge.  A full
memory of data of that energy carries ``e_j / (1 - lambda)`` in column j, so
``prior_share`` is the prior's information relative to the data's, per column:
scale-free, the same for any cell size, window or column scaling.  Well
excited directions move least (their information is many columns' worth);
collinear ones, whose information is far below any single column's, are held
near the prior.  A prior far from the cell still pulls every direction some:
in the SOC path it cost the cold LG runs more than it won on Panasonic
(docs/soc_experiments.md), so it is off by default.  The trace limit still
applies (the step only lowers P); the identifier's admissibility guard sees
the pulled theta like any other.

Every array carries the cell axis first; one call updates every cell.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .cells import all_cells, any_cell

__all__ = ["RlsConfig", "WeightedRls"]


@dataclass(frozen=True)
class RlsConfig:
    """The recursion's settings (module docstring).  The identifiers pass theirs from
    :meth:`~bms_estimator.core.identifier.IdentifierConfig.rls` (its ``trace_max`` and
    ``init_samples`` defaults differ from these, which serve a bare :class:`WeightedRls`)."""

    forgetting: float = 0.9995
    error_on: float = 0.0
    error_off: float = 0.0
    error_window: int = 30
    trace_max: float = 1e4
    init_samples: int = 300
    init_delta: float = 1e-9
    prior_share: float = 0.0  # stabilised forgetting: the prior's information relative to the data's (0 = off)
    prior_every: int = 30  # ... added every this many learning samples of a cell

    def __post_init__(self) -> None:
        if not 0.9 <= self.forgetting <= 1.0:
            raise ValueError(f"forgetting must be in [0.9, 1], got {self.forgetting}")
        if self.error_off > self.error_on:
            raise ValueError("error_off must not exceed error_on")
        if self.error_window < 1 or self.init_samples < 1:
            raise ValueError("error_window and init_samples must be >= 1")
        if self.trace_max <= 0:
            raise ValueError("trace_max must be positive")
        if not self.prior_share >= 0 or self.prior_every < 1:
            raise ValueError(f"prior_share must be >= 0 and prior_every >= 1, got {self.prior_share}, "
                             f"{self.prior_every}")


class WeightedRls:
    """Vectorised weighted RLS with turn-on/turn-off adaptation and a trace limit."""

    def __init__(self, n_cells: int, n_params: int, config: RlsConfig = RlsConfig()):
        self.config = config
        self.n_cells = int(n_cells)
        self.n_params = int(n_params)
        n, p = self.n_cells, self.n_params
        self.theta = np.zeros((n, p))
        # P is stored element-major, (p, p, N): each element a contiguous vector over the cells,
        # which makes the per-sample update twice as fast as on (N, p, p); ``P`` is that view
        self._pt = np.zeros((p, p, n))
        self.initialised = np.zeros(n, dtype=bool)
        self.adapting = np.ones(n, dtype=bool)
        self._R = np.zeros((n, p, p))
        self._r = np.zeros((n, p))
        self._init_count = np.zeros(n, dtype=np.int64)
        self.theta_ref = np.zeros((n, p))  # where the block ridge pulls theta0
        self._err2 = np.zeros((n, config.error_window))
        self._err_head = 0
        self._err_count = np.zeros(n, dtype=np.int64)
        self._eye = np.eye(p)
        self._group_starts: np.ndarray | None = None  # see set_groups
        self._one_cell_groups = False  # see set_groups
        self._since_prior = np.zeros(n, dtype=np.int64)  # learning samples since the last prior step

    def set_groups(self, sizes) -> None:
        """Cells in consecutive groups of ``sizes`` (independent packs side by side, e.g. the batch's
        stacked drives): the error window's ring head, which advances when any cell learns, is
        then kept per group, so that each group's results are those it has alone. Groups of one
        cell (the batch's stacked one-cell drives) also take a one-cell RLS's arithmetic for the
        products over the parameters, whose last bit numpy's kernels make depend on the width
        (:func:`_one_cell_gain_terms`). On a fresh RLS."""
        sizes = np.asarray(sizes, dtype=np.int64)
        if sizes.sum() != self.n_cells or np.any(sizes < 1):
            raise ValueError(f"groups of {sizes.tolist()} cells do not make the {self.n_cells} cells")
        self._group_starts = np.concatenate(([0], np.cumsum(sizes)[:-1]))
        self._group_of = np.repeat(np.arange(sizes.size), sizes)
        self._rows = np.arange(self.n_cells)
        self._err_head = np.full(sizes.size, int(self._err_head), dtype=np.int64)
        self._one_cell_groups = bool(self.n_cells > 1 and np.all(sizes == 1))

    @property
    def P(self) -> np.ndarray:
        """The covariance, ``(N, p, p)`` (a writable view of the element-major store)."""
        return np.moveaxis(self._pt, 2, 0)

    @P.setter
    def P(self, value: np.ndarray) -> None:
        self._pt = np.ascontiguousarray(np.moveaxis(np.asarray(value, dtype=float), 0, 2))

    # ------------------------------------------------------------------ update
    def update(self, phi: np.ndarray, y: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """One sample for every cell; ``mask`` (bool, N) selects the cells that may learn.

        Returns the a-priori error e (N,); NaN for cells still initialising.
        Cells whose init window completes in this call get theta0 and P0.
        """
        cfg = self.config
        lam = cfg.forgetting
        if mask is None:
            mask = np.ones(self.n_cells, dtype=bool)
        if self._one_cell_groups:  # each cell's regressor one contiguous row, as in a one-cell RLS: the
            phi = np.ascontiguousarray(phi)  # LIF's (N, p) is a transposed view, and a strided row sums otherwise
        e = y - np.einsum("np,np->n", phi, self.theta)

        every_init = all_cells(self.initialised)  # the usual sample: no cell in its block
        init_now = None if every_init else mask & ~self.initialised
        run = mask if every_init else mask & self.initialised  # before the block solve: its last sample is in theta0 already
        if init_now is not None and any_cell(init_now):
            self._accumulate(phi, y, init_now)
        if any_cell(run):
            # windowed error RMS drives turn-on/turn-off (only from learning samples)
            h = self._err_head
            if self._group_starts is None:
                self._err2[:, h] = e * e if all_cells(run) else np.where(run, e * e, self._err2[:, h])
                self._err_head = (h + 1) % cfg.error_window
            else:  # a head per group, advanced when a cell of that group learns
                at = (self._rows, h[self._group_of])
                self._err2[at] = np.where(run, e * e, self._err2[at])
                self._err_head = np.where(np.logical_or.reduceat(run, self._group_starts),
                                          (h + 1) % cfg.error_window, h)
            self._err_count += run
            if cfg.error_on > 0:  # the RMS only switches adaptation when a threshold is set
                filled = np.minimum(self._err_count, cfg.error_window)
                rms = np.sqrt(self._err2.sum(axis=1) / np.maximum(filled, 1))
                self.adapting = np.where(
                    rms > cfg.error_on, True, np.where(rms < cfg.error_off, False, self.adapting)
                )
            w = run & self.adapting
            if any_cell(w):
                self._rls_step(phi, e, w, lam)
                if cfg.prior_share > 0:
                    self._since_prior += w
                    due = self._since_prior >= cfg.prior_every
                    if any_cell(due):
                        self._prior_step(due)
        if all_cells(self.initialised):  # every cell running (the usual sample): no NaN to put in
            return e
        return np.where(self.initialised | init_now, e, np.nan) if init_now is not None else np.where(self.initialised, e, np.nan)

    @property
    def grouped(self) -> bool:
        """Whether the cells are in groups (:meth:`set_groups`)."""
        return self._group_starts is not None

    def group_any(self, mask: np.ndarray) -> np.ndarray | None:
        """With groups (:meth:`set_groups`): per cell, whether any cell of its group is in ``mask``; else None."""
        if self._group_starts is None:
            return None
        return np.logical_or.reduceat(np.asarray(mask, dtype=bool), self._group_starts)[self._group_of]

    def _rls_step(self, phi: np.ndarray, e: np.ndarray, w: np.ndarray, lam: float) -> None:
        # A step runs when any cell learns and touches the others too (gain 0, but the trace
        # limit); with groups, a group none of whose cells learns is left exactly as it was,
        # as it is when it runs alone
        live = self.group_any(w)
        hold = None if live is None or all_cells(live) else ~live
        if hold is not None:
            theta_held, p_held = self.theta[hold], self._pt[:, :, hold]
        self._rls_step_all(phi, e, w, lam)
        if hold is not None:
            self.theta[hold] = theta_held
            self._pt[:, :, hold] = p_held

    def _rls_step_all(self, phi: np.ndarray, e: np.ndarray, w: np.ndarray, lam: float) -> None:
        P = self._pt  # (p, p, N)
        phi_t = phi.T
        if self._one_cell_groups:
            pphi, denom = _one_cell_gain_terms(P, phi, lam)
        else:
            pphi = np.einsum("ijn,jn->in", P, phi_t)
            denom = lam + (phi_t * pphi).sum(axis=0)
        gain = pphi / denom
        every = all_cells(w)  # the usual case: no per-cell selects
        if not every:
            gain[:, ~w] = 0.0
        self.theta += (gain * e).T
        P -= np.multiply(gain[:, None, :], pphi[None, :, :])
        if every:
            P /= lam
        else:
            P /= np.where(w, lam, 1.0)
        # keep P bounded
        tr = np.einsum("iin->n", P)
        over = tr > self.config.trace_max
        if any_cell(over):
            P *= np.where(over, self.config.trace_max / np.where(tr > 0, tr, 1.0), 1.0)

    def prior_information(self, cells: np.ndarray) -> np.ndarray:
        """``Pi^-1`` (its diagonal, (n, p)) of the selected cells (lambda < 1): ``prior_share / (1 -
        lambda) e``, e the block start's mean column energy (module docstring), floored as the
        block ridge is."""
        cfg = self.config
        lam = cfg.forgetting
        n = self._init_count[cells].astype(float)
        weight = (1.0 - lam ** n) / (1.0 - lam)  # sum_k lambda^(n-k) over the block: what diag(R) sums
        energy = np.einsum("nii->ni", self._R[cells]) / np.maximum(weight, 1.0)[:, None]
        floor = np.maximum(energy.sum(axis=1) / self.n_params, 1e-300)[:, None] * 1e-3
        return cfg.prior_share / (1.0 - lam) * np.maximum(energy, floor)

    def _prior_step(self, due: np.ndarray) -> None:
        """The stabilised-forgetting step of the ``due`` cells (module docstring): the prior's
        information of the last ``prior_every`` samples added, theta pulled toward ``theta_ref``.
        Without forgetting (lambda = 1) the prior term ``(1 - lambda) Pi^-1`` is 0: nothing to do."""
        cfg = self.config
        idx = np.flatnonzero(due)
        self._since_prior[idx] = 0
        if cfg.forgetting >= 1.0:
            return
        a = (1.0 - cfg.forgetting ** cfg.prior_every) * self.prior_information(idx)  # diag of A
        P = np.moveaxis(self._pt[:, :, idx], 2, 0)  # (n, p, p)
        P_new = np.linalg.solve(self._eye + P * a[:, None, :], P)  # (I + P A)^-1 P
        P_new = 0.5 * (P_new + np.swapaxes(P_new, 1, 2))
        self.theta[idx] += np.einsum("nij,nj->ni", P_new, a * (self.theta_ref[idx] - self.theta[idx]))
        self._pt[:, :, idx] = np.moveaxis(P_new, 0, 2)

    def pseudo_update(self, h: np.ndarray, y: np.ndarray, mask: np.ndarray) -> None:
        """A prior as a pseudo-measurement y = h' theta (no forgetting, no error window)."""
        run = mask & self.initialised
        if any_cell(run):
            e = y - np.einsum("np,np->n", h, self.theta)
            self._rls_step(h, np.where(run, e, 0.0), run, 1.0)

    def _accumulate(self, phi: np.ndarray, y: np.ndarray, sel: np.ndarray) -> None:
        lam = self.config.forgetting
        s = sel[:, None]
        self._R = np.where(s[:, :, None], lam * self._R + phi[:, :, None] * phi[:, None, :], self._R)
        self._r = np.where(s, lam * self._r + phi * y[:, None], self._r)
        self._init_count += sel
        done = sel & (self._init_count >= self.config.init_samples)
        if any_cell(done):
            self.initialise_from_block(done)

    def extend_block(self, cells: np.ndarray) -> None:
        """Undo the start of the selected cells: their block keeps accumulating.

        For a caller that rejects theta0 (e.g. a non-physical one from a block too
        short to see the slow pole); the block is solved again after each further sample.
        """
        self.initialised[cells] = False
        self.theta[cells] = 0.0
        self.P[cells] = 0.0
        self._since_prior[cells] = 0

    def restart(self, cells: np.ndarray) -> None:
        """Forget the selected cells' estimate and start a fresh initialisation block."""
        self.extend_block(cells)
        self._R[cells] = 0.0
        self._r[cells] = 0.0
        self._init_count[cells] = 0

    @property
    def block_samples(self) -> np.ndarray:
        """Samples accumulated in each cell's initialisation block so far."""
        return self._init_count

    def initialise_from_block(self, cells: np.ndarray) -> None:
        """theta0, P0 by block least squares over the accumulated window (selected cells)."""
        idx = np.flatnonzero(cells)
        R = self._R[idx]
        # a ridge relative to each column's own energy (Jacobi scaling) keeps P0 finite for a
        # window with no excitation in some column without biasing a badly scaled one
        diag = np.einsum("nii->ni", R)
        floor = np.maximum(diag.sum(axis=1) / self.n_params, 1e-300)[:, None] * 1e-3
        delta = self.config.init_delta * np.maximum(diag, floor)
        A = R + delta[:, :, None] * self._eye
        P0 = np.linalg.inv(A)
        theta0 = np.einsum("nij,nj->ni", P0, self._r[idx] + delta * self.theta_ref[idx])
        tr = np.einsum("nii->n", P0)
        P0 *= np.minimum(1.0, self.config.trace_max / np.maximum(tr, 1e-300))[:, None, None]
        self.theta[idx] = theta0
        self.P[idx] = P0
        self.initialised[idx] = True

    # --------------------------------------------------------------- utilities
    def reset_theta(self, cells: np.ndarray, theta: np.ndarray) -> None:
        """Put theta of the selected cells back (e.g. to the last admissible estimate)."""
        self.theta[cells] = theta[cells]

    def state_dict(self) -> dict[str, np.ndarray]:
        return {
            "theta": self.theta.copy(),
            "P": self.P.copy(),
            "initialised": self.initialised.copy(),
            "adapting": self.adapting.copy(),
            "R": self._R.copy(),
            "r": self._r.copy(),
            "init_count": self._init_count.copy(),
            "err2": self._err2.copy(),
            # (with groups: per cell, its group's head)
            "err_head": (np.array(self._err_head) if self._group_starts is None
                         else self._err_head[self._group_of].copy()),
            "err_count": self._err_count.copy(),
            "since_prior": self._since_prior.copy(),
        }

    def load_state_dict(self, s: dict[str, np.ndarray]) -> None:
        n, p = self.n_cells, self.n_params
        expect = {"theta": (n, p), "P": (n, p, p), "R": (n, p, p), "r": (n, p)}
        for key, shape in expect.items():
            if np.shape(s[key]) != shape:
                raise ValueError(f"RLS state {key!r} has shape {np.shape(s[key])}, expected {shape}")
        if np.shape(s["err2"]) != self._err2.shape:
            raise ValueError("RLS error window does not match the configuration")
        self.theta = np.array(s["theta"], dtype=float)
        self.P = np.array(s["P"], dtype=float)
        self.initialised = np.array(s["initialised"], dtype=bool)
        self.adapting = np.array(s["adapting"], dtype=bool)
        self._R = np.array(s["R"], dtype=float)
        self._r = np.array(s["r"], dtype=float)
        self._init_count = np.array(s["init_count"], dtype=np.int64)
        self._err2 = np.array(s["err2"], dtype=float)
        self._err_head = int(s["err_head"])
        self._err_count = np.array(s["err_count"], dtype=np.int64)
        # (a state saved before stabilised forgetting existed: its first step a full period on)
        self._since_prior = np.array(s.get("since_prior", np.zeros(n)), dtype=np.int64)


def _one_cell_gain_terms(pt: np.ndarray, phi: np.ndarray, lam: float) -> tuple[np.ndarray, np.ndarray]:
    """``P phi`` (p, N) and ``lam + phi' P phi`` (N,) with each cell's arithmetic that of a one-cell RLS.

    For ``N = 1`` numpy's ``einsum("ijn,jn->in")`` sums each row's ``p`` products as one contiguous
    run (its dot kernel); for ``N >= 2`` the cells are the inner loop and the ``p`` products are
    added in another order: a cell's last bit differs (in 1964 of 2000 random draws, numpy 2.4).
    Cell-major, ``einsum("nij,nj->ni")`` sums each cell's products as the one-cell call does, and
    ``phi' P phi`` is each cell's contiguous row summed, as the one-cell ``(p, 1)`` column is.
    (Checked bit for bit: ``tests/fleet/test_fleet_stack.py``.)
    """
    phi = np.ascontiguousarray(phi)
    pphi = np.einsum("nij,nj->ni", np.ascontiguousarray(np.moveaxis(pt, 2, 0)), phi)
    denom = lam + (phi * pphi).sum(axis=1)
    return np.ascontiguousarray(pphi.T), denom
