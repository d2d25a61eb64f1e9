"""Equivalent-circuit model (ECM) of a cell: R0 plus m RC pairs, simulated exactly.

Model (current ``i`` positive = charge)::

    v(t)   = OCV(soc(t)) + R0 i(t) + sum_j x_j(t) + c0
    x_j'   = -x_j / (R_j C_j) + i / C_j                 (tau_j = R_j C_j)
    soc'   = i / (3600 Q)

Zero-order-hold discretisation with step ``Ts`` (the current is held over
``[k Ts, (k+1) Ts)``) is exact for piecewise-constant current::

    p_j        = exp(-Ts / tau_j)
    x_j[k+1]   = p_j x_j[k] + R_j (1 - p_j) i[k]
    v[k]       = OCV(soc[k]) + R0 i[k] + sum_j x_j[k] + c0          (output="sample")

Measured data that was resampled by averaging over each step is better matched
by the step-mean of the RC voltage (``output="mean"``)::

    mean_j[k]  = x_j[k] g_j + R_j i[k] (1 - g_j),   g_j = tau_j (1 - p_j) / Ts

Parameters may be constant or vary per sample (shape ``(n,)`` or ``(n, m)``),
which is how parameters looked up by SOC, or an online estimator's trajectory,
are simulated.  Cells are independent: pass 2-D current ``(n, N)`` and
parameters broadcastable to it to simulate N cells at once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal

import numpy as np
from scipy.signal import lfilter

ArrayLike = np.ndarray | float

__all__ = ["EcmParams", "EcmSimulation", "simulate_ecm", "soc_from_current"]


@dataclass(frozen=True)
class EcmParams:
    """Physical parameters of an R0 + m RC cell model.

    ``r_ohm`` and ``tau_s`` have a trailing axis of length m (RC pairs, sorted
    fast first by the estimators); every field may carry leading axes (time,
    cells) that broadcast together.
    """

    r0_ohm: np.ndarray
    r_ohm: np.ndarray
    tau_s: np.ndarray
    c0_v: np.ndarray | float = 0.0

    @classmethod
    def from_rc(
        cls,
        r0_ohm: ArrayLike,
        r_ohm: ArrayLike,
        tau_s: ArrayLike,
        c0_v: ArrayLike = 0.0,
    ) -> "EcmParams":
        r = np.atleast_1d(np.asarray(r_ohm, dtype=float))
        tau = np.atleast_1d(np.asarray(tau_s, dtype=float))
        if r.shape != tau.shape:
            raise ValueError(f"r_ohm shape {r.shape} does not match tau_s shape {tau.shape}")
        return cls(np.asarray(r0_ohm, dtype=float), r, tau, np.asarray(c0_v, dtype=float))

    @property
    def n_rc(self) -> int:
        return int(self.r_ohm.shape[-1])


@dataclass(frozen=True)
class EcmSimulation:
    voltage_v: np.ndarray  # terminal voltage, shape of the current
    rc_voltage_v: np.ndarray  # RC-pair voltages, current shape + (m,)
    soc: np.ndarray  # SOC used for the OCV, shape of the current


def soc_from_current(
    current_a: np.ndarray, dt_s: float, capacity_ah: ArrayLike, soc0: ArrayLike
) -> np.ndarray:
    """Coulomb counting: soc[k] = soc0 + sum_{l<k} i[l] Ts / (3600 Q) (charge at sample k's start)."""
    current_a = np.asarray(current_a, dtype=float)
    charge = np.cumsum(current_a, axis=0) * (dt_s / 3600.0)
    charge = np.concatenate([np.zeros_like(charge[:1]), charge[:-1]], axis=0)
    return np.asarray(soc0, dtype=float) + charge / np.asarray(capacity_ah, dtype=float)


def simulate_ecm(
    current_a: np.ndarray,
    dt_s: float,
    params: EcmParams,
    ocv: Callable[[np.ndarray], np.ndarray] | None = None,
    *,
    soc: np.ndarray | None = None,
    soc0: ArrayLike = 1.0,
    capacity_ah: ArrayLike | None = None,
    x0: np.ndarray | None = None,
    output: Literal["sample", "mean"] = "sample",
) -> EcmSimulation:
    """Simulate the terminal voltage of the ECM for a current profile.

    Args:
        current_a: current, shape ``(n,)`` or ``(n, N)``; positive = charge.
        dt_s: sample step.
        params: constant or per-sample parameters (leading axis n when they vary).
        ocv: OCV(soc) function; ``None`` simulates the overpotential only (OCV = 0).
        soc: SOC trajectory to read the OCV at; computed by coulomb counting
            from ``soc0`` and ``capacity_ah`` when omitted.
        x0: initial RC voltages, shape ``current.shape[1:] + (m,)``; zero when omitted.
        output: ``"sample"`` for point samples, ``"mean"`` for step-averaged data.
    """
    i = np.asarray(current_a, dtype=float)
    if i.ndim not in (1, 2):
        raise ValueError(f"current must be 1-D or 2-D (time, cells), got shape {i.shape}")
    if not np.all(np.isfinite(i)):
        raise ValueError("current contains NaN or inf")
    n = i.shape[0]
    m = params.n_rc
    r = np.asarray(params.r_ohm, dtype=float)
    tau = np.asarray(params.tau_s, dtype=float)
    if np.any(tau <= 0) or np.any(r < 0):
        raise ValueError("RC pairs need tau_s > 0 and r_ohm >= 0")
    p = np.exp(-dt_s / tau)
    gain = r * (1.0 - p)
    g_mean = tau * (1.0 - p) / dt_s

    varying = r.ndim > 1 and r.shape[0] == n and n > 1
    ii = i[..., None]  # (n, [N,] 1)
    if not varying:
        # constant parameters: one IIR filter per pair (and per cell), exact ZOH
        shape_out = i.shape + (m,)
        rc = np.empty(shape_out)
        pb = np.broadcast_to(p, i.shape[1:] + (m,))
        gb = np.broadcast_to(gain, i.shape[1:] + (m,))
        x_init = np.zeros(i.shape[1:] + (m,)) if x0 is None else np.broadcast_to(x0, i.shape[1:] + (m,))
        for idx in np.ndindex(*pb.shape):
            cell_idx = idx[:-1]
            col = i[(slice(None),) + cell_idx]
            pj, gj, xj = float(pb[idx]), float(gb[idx]), float(x_init[idx])
            # x[k] = pj x[k-1] + gj i[k-1]; x[0] = xj
            driven = lfilter([0.0, gj], [1.0, -pj], col)
            rc[(slice(None),) + idx] = driven + xj * pj ** np.arange(n)
    else:
        rc = np.empty(i.shape + (m,))
        x = np.zeros(i.shape[1:] + (m,)) if x0 is None else np.array(x0, dtype=float)
        pv = np.broadcast_to(p, i.shape + (m,)) if p.ndim > 1 else p
        gv = np.broadcast_to(gain, i.shape + (m,)) if gain.ndim > 1 else gain
        for k in range(n):
            rc[k] = x
            x = pv[k] * x + gv[k] * ii[k]
    if output == "mean":
        gm = np.broadcast_to(g_mean, rc.shape) if np.ndim(g_mean) > 1 else g_mean
        rv = np.broadcast_to(r, rc.shape) if r.ndim > 1 else r
        rc_out = rc * gm + rv * ii * (1.0 - gm)
    elif output == "sample":
        rc_out = rc
    else:
        raise ValueError(f"output must be 'sample' or 'mean', got {output!r}")

    if soc is None:
        if ocv is not None and capacity_ah is None:
            raise ValueError("capacity_ah is needed to coulomb-count the SOC for the OCV")
        soc = soc_from_current(i, dt_s, capacity_ah if capacity_ah is not None else 1.0, soc0)
    soc = np.broadcast_to(np.asarray(soc, dtype=float), i.shape)
    ocv_v = 0.0 if ocv is None else np.asarray(ocv(soc), dtype=float)
    r0 = np.asarray(params.r0_ohm, dtype=float)
    c0 = np.asarray(params.c0_v, dtype=float)
    v = ocv_v + r0 * i + rc_out.sum(axis=-1) + c0
    return EcmSimulation(voltage_v=np.asarray(v), rc_voltage_v=rc_out, soc=np.asarray(soc))
