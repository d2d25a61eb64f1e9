"""Mappings between regression parameters (theta) and the physical 2-RC model.

Continuous time (the paper's ODE, current positive = charge)::

    v_o = (R0 + b1/(s+a1) + b2/(s+a2)) i + c0,    a_j = 1/(R_j C_j),  b_j = 1/C_j

    v_o'' = th1 v_o' + th2 v_o + th3 i'' + th4 i' + th5 i + th6

    th1 = -(a1 + a2)              th2 = -a1 a2
    th3 = R0                      th4 = R0 (a1 + a2) + b1 + b2
    th5 = R0 a1 a2 + b1 a2 + b2 a1
    th6 = a1 a2 c0

Inverse: a1, a2 are the roots of ``s^2 + th1 s - th2 = 0`` (real, positive and
distinct for a physical cell), ``b1 = (D - a1 B)/(a2 - a1)``, ``b2 = B - b1``
with ``B = th4 - R0 (a1 + a2)`` and ``D = th5 - R0 a1 a2``; ``c0 = -th6 / th2``.

Discrete time (the ARX baseline, ZOH-exact RC pairs with poles p_j = exp(-Ts/tau_j))::

    v_o[k] = A1 v_o[k-1] + A2 v_o[k-2] + B0 i[k] + B1 i[k-1] + B2 i[k-2] + K

    A1 = p1 + p2,   A2 = -p1 p2,   B0 = R0
    B1 = -R0 (p1 + p2) + g1 + g2,  B2 = R0 p1 p2 - g1 p2 - g2 p1,  g_j = R_j (1 - p_j)
    K  = c0 (1 - A1 - A2)

All functions are vectorised over leading axes (cells, time).  A parameter set is
*admissible* when every R and C is positive and finite, the poles are real and
distinct, and both time constants lie inside ``[tau_min_s, tau_max_s]``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = [
    "PhysicalParams",
    "ct_theta_from_physical",
    "ct_physical_from_theta",
    "ct_physical_from_rows",
    "ct_c0_from_theta",
    "dt_theta_from_physical",
    "dt_physical_from_theta",
]


@dataclass(frozen=True)
class PhysicalParams:
    """2-RC parameters, pairs sorted fast first; arrays share one shape."""

    r0_ohm: np.ndarray
    r1_ohm: np.ndarray
    c1_f: np.ndarray
    r2_ohm: np.ndarray
    c2_f: np.ndarray
    c0_v: np.ndarray
    admissible: np.ndarray  # bool: passes the physical checks
    # bool: the checks that do not involve c0 (the CT mapping's; None where not known). c0 alone
    # moves when an OCV bias is shifted out of the model: with this, c0 and the flag are redone alone
    dynamics_ok: np.ndarray | None = field(default=None, repr=False, compare=False)

    @property
    def tau1_s(self) -> np.ndarray:
        return self.r1_ohm * self.c1_f

    @property
    def tau2_s(self) -> np.ndarray:
        return self.r2_ohm * self.c2_f

    def as_dict(self) -> dict[str, np.ndarray]:
        return {
            "r0_ohm": self.r0_ohm,
            "r1_ohm": self.r1_ohm,
            "c1_f": self.c1_f,
            "r2_ohm": self.r2_ohm,
            "c2_f": self.c2_f,
            "c0_v": self.c0_v,
            "tau1_s": self.tau1_s,
            "tau2_s": self.tau2_s,
        }

    def select(self, mask: np.ndarray, other: "PhysicalParams") -> "PhysicalParams":
        """Elementwise: self where mask, else other."""
        both = self.dynamics_ok is not None and other.dynamics_ok is not None
        return PhysicalParams(
            *(np.where(mask, a, b) for a, b in zip(self._arrays(), other._arrays())),
            admissible=np.where(mask, self.admissible, other.admissible),
            dynamics_ok=np.where(mask, self.dynamics_ok, other.dynamics_ok) if both else None,
        )

    def with_c0(self, c0_v: np.ndarray) -> "PhysicalParams":
        """The same dynamics with another c0 (needs :attr:`dynamics_ok`): admissible is
        ``dynamics_ok & isfinite(c0)``, what :func:`ct_physical_from_theta` gives for a theta
        that differs in th6 alone."""
        if self.dynamics_ok is None:
            raise ValueError("with_c0 needs the dynamics' checks (dynamics_ok)")
        return PhysicalParams(*self._arrays()[:5], c0_v, admissible=self.dynamics_ok & np.isfinite(c0_v),
                              dynamics_ok=self.dynamics_ok)

    def _arrays(self) -> tuple[np.ndarray, ...]:
        return (self.r0_ohm, self.r1_ohm, self.c1_f, self.r2_ohm, self.c2_f, self.c0_v)


R_MIN_OHM = 1e-9


def _check_dynamics(
    r: np.ndarray,
    tau1: np.ndarray,
    tau2: np.ndarray,
    real: np.ndarray,
    tau_min_s: float,
    tau_max_s: float,
) -> np.ndarray:
    """The checks but c0's: real poles, finite resistances ``r`` = (R0, R1, R2) stacked (3, ...) above a
    nano-ohm, ordered time constants in range."""
    # a resistance below a nano-ohm is no cell's (and its C = tau / R overflows)
    fine = np.isfinite(r)
    fine &= r > R_MIN_OHM
    ok = real & fine[0] & fine[1] & fine[2]
    ok &= (tau1 >= tau_min_s) & (tau2 <= tau_max_s) & (tau1 < tau2)
    return ok


def _check(
    r0: np.ndarray,
    r1: np.ndarray,
    r2: np.ndarray,
    tau1: np.ndarray,
    tau2: np.ndarray,
    c0: np.ndarray,
    real: np.ndarray,
    tau_min_s: float,
    tau_max_s: float,
) -> np.ndarray:
    return _check_dynamics(np.stack(np.broadcast_arrays(r0, r1, r2)), tau1, tau2, real, tau_min_s, tau_max_s) & np.isfinite(c0)


def ct_theta_from_physical(
    r0_ohm, r1_ohm, tau1_s, r2_ohm, tau2_s, c0_v=0.0
) -> np.ndarray:
    """theta (..., 6) of the CT ODE for given physical parameters."""
    r0, r1, t1, r2, t2, c0 = np.broadcast_arrays(
        *(np.asarray(x, dtype=float) for x in (r0_ohm, r1_ohm, tau1_s, r2_ohm, tau2_s, c0_v))
    )
    a1, a2 = 1.0 / t1, 1.0 / t2
    b1, b2 = r1 / t1, r2 / t2  # b_j = 1/C_j = R_j / tau_j
    th = np.stack(
        [
            -(a1 + a2),
            -a1 * a2,
            r0,
            r0 * (a1 + a2) + b1 + b2,
            r0 * a1 * a2 + b1 * a2 + b2 * a1,
            a1 * a2 * c0,
        ],
        axis=-1,
    )
    return th


def ct_physical_from_theta(
    theta: np.ndarray, *, tau_min_s: float = 0.0, tau_max_s: float = np.inf
) -> PhysicalParams:
    """Physical 2-RC parameters from CT theta (..., 6); non-physical ones flagged."""
    th = np.asarray(theta, dtype=float)
    return ct_physical_from_rows(np.moveaxis(th, -1, 0), tau_min_s=tau_min_s, tau_max_s=tau_max_s)


def ct_physical_from_rows(
    th: np.ndarray, *, tau_min_s: float = 0.0, tau_max_s: float = np.inf
) -> PhysicalParams:
    """:func:`ct_physical_from_theta` of theta given parameter-first, ``th[k]`` = theta[..., k] (6, ...).

    The per-sample path: with ``th`` contiguous every operation runs on contiguous rows, and
    the two poles (and the pairs' R, C, tau) are rows of one array, each taken in one call.
    The arithmetic is elementwise and the same for every element, as the module docstring
    writes it.
    """
    th1, th2, th3, th4, th5, th6 = (th[k, ...] for k in range(6))  # (0-d arrays for one theta, as theta[..., k])
    disc = th1 * th1 + 4.0 * th2
    pos = disc > 0
    real = (th1 < 0) & (th2 < 0) & pos
    sq = np.sqrt(np.where(pos, disc, 0.0))
    # roots of s^2 + th1 s - th2: a = (-th1 -+ sq)/2 ; a[0] the fast (larger) pole, a[1] the slow one
    minus_th1 = -th1
    a = np.empty((2,) + th1.shape)
    a_fast, a_slow = a[0, ...], a[1, ...]
    np.add(minus_th1, sq, out=a_fast)
    np.subtract(minus_th1, sq, out=a_slow)
    a *= 0.5
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        r0 = th3
        big_b = th4 - r0 * (a_fast + a_slow)
        big_d = th5 - r0 * a_fast * a_slow
        b = np.empty_like(a)  # b_j = 1 / C_j
        np.divide(big_d - a_fast * big_b, a_slow - a_fast, out=b[0, ...])
        np.subtract(big_b, b[0, ...], out=b[1, ...])
        r = np.empty((3,) + a.shape[1:])  # R0, R1, R2 (checked together)
        r[0] = r0
        np.divide(b, a, out=r[1:])
        c = 1.0 / b  # c1, c2
        tau = 1.0 / a  # tau1, tau2
        c0 = _c0(th6, th2)
    r1, r2, c1, c2, tau1, tau2 = r[1], r[2], c[0], c[1], tau[0], tau[1]
    dynamics_ok = _check_dynamics(r, tau1, tau2, real, tau_min_s, tau_max_s)
    return PhysicalParams(r0, r1, c1, r2, c2, c0, dynamics_ok & np.isfinite(c0), dynamics_ok=dynamics_ok)


def ct_c0_from_theta(th6: np.ndarray, th2: np.ndarray) -> np.ndarray:
    """c0 = -th6 / th2 (the CT steady state's offset; inf/NaN where th2 is 0, without a warning)."""
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        return _c0(th6, th2)


def _c0(th6: np.ndarray, th2: np.ndarray) -> np.ndarray:
    """``-th6 / th2`` (under the caller's errstate)."""
    return -th6 / th2


def dt_theta_from_physical(
    r0_ohm, r1_ohm, tau1_s, r2_ohm, tau2_s, c0_v=0.0, *, dt_s: float = 1.0
) -> np.ndarray:
    """theta (..., 6) of the ARX model [A1, A2, B0, B1, B2, K]."""
    r0, r1, t1, r2, t2, c0 = np.broadcast_arrays(
        *(np.asarray(x, dtype=float) for x in (r0_ohm, r1_ohm, tau1_s, r2_ohm, tau2_s, c0_v))
    )
    p1, p2 = np.exp(-dt_s / t1), np.exp(-dt_s / t2)
    g1, g2 = r1 * (1 - p1), r2 * (1 - p2)
    a1, a2 = p1 + p2, -p1 * p2
    return np.stack(
        [a1, a2, r0, -r0 * (p1 + p2) + g1 + g2, r0 * p1 * p2 - g1 * p2 - g2 * p1, c0 * (1 - a1 - a2)],
        axis=-1,
    )


def dt_physical_from_theta(
    theta: np.ndarray, *, dt_s: float = 1.0, tau_min_s: float = 0.0, tau_max_s: float = np.inf
) -> PhysicalParams:
    """Physical 2-RC parameters from ARX theta (..., 6); non-physical ones flagged."""
    th = np.asarray(theta, dtype=float)
    a1, a2, b0, b1, b2, k = (th[..., j] for j in range(6))
    disc = a1 * a1 + 4.0 * a2  # z^2 - a1 z - a2 = 0
    sq = np.sqrt(np.where(disc > 0, disc, 0.0))
    p_slow = 0.5 * (a1 + sq)
    p_fast = 0.5 * (a1 - sq)
    real = (disc > 0) & (p_fast > 0) & (p_slow < 1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        r0 = b0
        big_b = b1 + r0 * (p_fast + p_slow)
        big_d = r0 * p_fast * p_slow - b2
        # g_fast p_slow + g_slow p_fast = D ; g_fast + g_slow = B
        g_fast = (big_d - big_b * p_fast) / (p_slow - p_fast)
        g_slow = big_b - g_fast
        r1 = g_fast / (1 - p_fast)
        r2 = g_slow / (1 - p_slow)
        tau1 = -dt_s / np.log(np.where(p_fast > 0, p_fast, np.nan))
        tau2 = -dt_s / np.log(np.where(p_slow > 0, p_slow, np.nan))
        c1 = tau1 / r1
        c2 = tau2 / r2
        c0 = k / (1 - a1 - a2)
    ok = _check(r0, r1, r2, tau1, tau2, c0, real, tau_min_s, tau_max_s)
    ok &= np.isfinite(tau1) & np.isfinite(tau2)
    return PhysicalParams(r0, r1, c1, r2, c2, c0, ok)
