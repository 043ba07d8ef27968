r"""Per-axis recursions of the nearly-constant-velocity model: a structure-exploiting kernel.

A :class:`~torchsvs.models.ConstantVelocity` model with a diagonal ``R`` (and a prior without
cross-axis covariance) is ``m`` independent two-state problems, one per axis: state
:math:`(p, v)`, :math:`F = [[1, T], [0, 1]]`, :math:`Q = q[[T^3/3, T^2/2], [T^2/2, T]]`. The
Kalman filter, the SVSF (``H⁺`` mode or finite-difference velocities) and the RTS/SVSS backward
recursion then act on 2×2 blocks, written here element by element on ``[B, (T,) m]`` tensors:
a few dozen elementwise operations per step instead of batched 4×4 (or 6×6) matrix products,
which on a CPU cost far more per element than the arithmetic. Results are exactly the general
path's (tested to 1e-9 in float64): the estimators pick this kernel by themselves.

Every axis has a two-component corrector measurement :math:`y = (y_p, y_v)` with ``H = I``;
position-only correctors (Kalman filter, the SVSF's ``H⁺`` mode) have :math:`y_v` always missing.
A 2×2 block is a tuple of ``[..., m]`` tensors: :class:`Sym2` ``(a, b, c)`` for
``[[a, b], [b, c]]`` and :class:`Mat2` ``(a, b, c, d)`` for ``[[a, b], [c, d]]``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.linalg import svsf_gain_ratio


class Sym2(NamedTuple):
    """A symmetric 2×2 block ``[[a, b], [b, c]]``."""

    a: Tensor
    b: Tensor
    c: Tensor


class Mat2(NamedTuple):
    """A 2×2 block ``[[a, b], [c, d]]``."""

    a: Tensor
    b: Tensor
    c: Tensor
    d: Tensor


def full(S: Sym2) -> Mat2:
    return Mat2(S.a, S.b, S.b, S.c)


def mm(X: Mat2, Y: Mat2) -> Mat2:
    return Mat2(
        X.a * Y.a + X.b * Y.c,
        X.a * Y.b + X.b * Y.d,
        X.c * Y.a + X.d * Y.c,
        X.c * Y.b + X.d * Y.d,
    )


def t(X: Mat2) -> Mat2:
    return Mat2(X.a, X.c, X.b, X.d)


def add(*blocks: Mat2) -> Mat2:
    return Mat2(*(sum(parts[1:], parts[0]) for parts in zip(*blocks, strict=True)))


def sandwich(X: Mat2, S: Mat2) -> Sym2:
    """``X S Xᵀ``, symmetrised."""
    P = mm(mm(X, S), t(X))
    return Sym2(P.a, 0.5 * (P.b + P.c), P.d)


def mv(X: Mat2, u: tuple[Tensor, Tensor]) -> tuple[Tensor, Tensor]:
    return X.a * u[0] + X.b * u[1], X.c * u[0] + X.d * u[1]


def inverse(S: Sym2) -> Sym2:
    det = S.a * S.c - S.b * S.b
    return Sym2(S.c / det, -S.b / det, S.a / det)


def transition(T: Tensor) -> Mat2:
    one, zero = torch.ones_like(T), torch.zeros_like(T)
    return Mat2(one, T, zero, one)


def process_noise(q: Tensor, T: Tensor) -> Sym2:
    """``Q`` of Eq. (48), Chen et al. 2020, per axis."""
    return Sym2(q * T**3 / 3, q * T**2 / 2, q * T)


class AxisMeasurements(NamedTuple):
    """A corrector's measurements per axis, ``[B, T, m]`` each (NaN where missing)."""

    position: Tensor
    velocity: Tensor  #: all NaN for position-only correctors
    noise: Sym2  #: R per axis: ``(r_pp, r_pv, r_vv)``, ``[m]`` or ``[B, T, m]`` each


class AxisResult(NamedTuple):
    """A filter pass per axis, stacked over time: ``[B, T, m]`` tensors."""

    mean: tuple[Tensor, Tensor]  #: (p, v) filtered
    cov: Sym2
    pred_mean: tuple[Tensor, Tensor]
    pred_cov: Sym2
    innovation: tuple[Tensor, Tensor]  #: a-priori, 0 where missing
    gain: Mat2  #: per axis, columns (position, velocity measurement)
    observed: tuple[Tensor, Tensor]  #: masks of (y_p, y_v)
    noise: Sym2  #: R per axis as used (identity on missing components, as mask_covariance)
    interval: Tensor  #: T of each step, [B, T, 1] or 0-d
    post_innovation: tuple[Tensor, Tensor] | None = None
    log_likelihood: Tensor | None = None  #: [B, T] summed over axes


def _masked_noise(R: Sym2, seen_p: Tensor, seen_v: Tensor) -> Sym2:
    """``R`` with an identity on missing components (as :func:`~torchsvs.linalg.mask_covariance`
    does)."""
    p, v = seen_p.to(R.a.dtype), seen_v.to(R.a.dtype)
    return Sym2(R.a * p + (1 - p), R.b * p * v, R.c * v + (1 - v))


def _at(x: Tensor, t: int) -> Tensor:
    return x[:, t] if x.ndim == 3 else x


def joseph(P: Sym2, K: Mat2, R: Sym2) -> Sym2:
    """``(I − K) P (I − K)ᵀ + K R Kᵀ`` (``H = I`` per axis; masked components have zero columns
    of ``K``)."""
    A = Mat2(1 - K.a, -K.b, -K.c, 1 - K.d)
    X, Y = sandwich(A, full(P)), sandwich(K, full(R))
    return Sym2(X.a + Y.a, X.b + Y.b, X.c + Y.c)


def run_axes(
    y: AxisMeasurements,
    x0: tuple[Tensor, Tensor],
    P0: Sym2,
    q: Tensor,
    interval: Tensor,
    rule: str,
    psi: Tensor | None = None,
    gamma: Tensor | None = None,
) -> AxisResult:
    """The forward pass of every axis.

    Args:
        y: the corrector's measurements per axis.
        x0, P0: the prior per axis, ``[B, m]`` each.
        q: process noise spectral density (0-d).
        interval: ``T`` per step, 0-d or ``[B, T]``.
        rule: ``"kalman"`` (position-only corrector, gain ``P Hᵀ S⁻¹``, Eqs. (14)-(16), Chen et
            al. 2020) or ``"svsf"`` (``K = diag(ratio)`` on the observed components, Eq. (23)
            with ``H⁺ = I``; the ``H⁺`` mode has no velocity measurements).
        psi: boundary layer ``[2, m]`` (rows: position, velocity widths) or per step
            ``[B, T, 2, m]``; gamma: memory (0-d). For ``"svsf"``.
    """
    B, steps, m = y.position.shape
    dtype = y.position.dtype
    seen_p, seen_v = ~torch.isnan(y.position), ~torch.isnan(y.velocity)
    # Everything that does not depend on the estimates, for all steps at once.
    fp_all, fv_all = seen_p.to(dtype), seen_v.to(dtype)
    yp_all, yv_all = y.position.nan_to_num(0.0), y.velocity.nan_to_num(0.0)
    R_all = _masked_noise(y.noise, seen_p, seen_v)
    T_all = interval.unsqueeze(-1) if interval.ndim == 2 else interval
    Q_all = process_noise(q, T_all)
    width_p = width_v = memory_rate = torch.zeros(())
    if rule == "svsf":
        assert psi is not None and gamma is not None
        width_p, width_v, memory_rate = psi[..., 0, :], psi[..., 1, :], gamma
    p, v = x0
    a, b, c = P0
    memory_p = memory_v = torch.zeros(B, m, dtype=dtype)
    out: dict[str, list] = {k: [] for k in ("x", "P", "xp", "Pp", "e", "K", "ep", "ll")}
    log_2pi = math.log(2 * math.pi)
    for k in range(steps):
        T = _at(T_all, k)
        # Prediction, Eqs. (11)-(12): F P Fᵀ + Q with F = [[1, T], [0, 1]].
        p_pred, v_pred = p + T * v, v
        bT = b + T * c
        a1 = a + T * (b + bT) + _at(Q_all.a, k)
        b1 = bT + _at(Q_all.b, k)
        c1 = c + _at(Q_all.c, k)
        fp, yp = fp_all[:, k], yp_all[:, k]
        rp = _at(R_all.a, k)
        ep = (yp - p_pred) * fp
        if rule == "kalman":
            S = a1 * fp + rp  # 1 where missing (the masked identity)
            k1, k2 = a1 * fp / S, b1 * fp / S
            # Joseph form with K = [k1, k2]ᵀ, H = [1, 0].
            one_k1 = 1 - k1
            a2 = one_k1 * one_k1 * a1 + k1 * k1 * rp
            b2 = one_k1 * (b1 - k2 * a1) + k1 * k2 * rp
            c2 = c1 - 2 * k2 * b1 + k2 * k2 * (a1 + rp)
            p, v = p_pred + k1 * ep, v_pred + k2 * ep
            out["ll"].append((-0.5 * (ep * ep / S + S.log() + fp * log_2pi)).sum(-1))
            zero = torch.zeros_like(k1)
            K = Mat2(k1, zero, k2, zero)
            ev = zero
        else:
            fv, yv = fv_all[:, k], yv_all[:, k]
            ev = (yv - v_pred) * fv
            wp = width_p[:, k] if width_p.ndim == 3 else width_p
            wv = width_v[:, k] if width_v.ndim == 3 else width_v
            kp = svsf_gain_ratio(ep, memory_p, wp, memory_rate) * fp
            kv = svsf_gain_ratio(ev, memory_v, wv, memory_rate) * fv
            # Joseph form with a diagonal gain, H = I: (I − K) P (I − K)ᵀ + K R Kᵀ.
            one_p, one_v = 1 - kp, 1 - kv
            a2 = one_p * one_p * a1 + kp * kp * rp
            b2 = one_p * one_v * b1 + kp * kv * _at(R_all.b, k)
            c2 = one_v * one_v * c1 + kv * kv * _at(R_all.c, k)
            p, v = p_pred + kp * ep, v_pred + kv * ev
            # Eq. (24): the a-posteriori innovation, carried where missing.
            memory_p = torch.where(seen_p[:, k], yp - p, memory_p)
            memory_v = torch.where(seen_v[:, k], yv - v, memory_v)
            out["ep"].append((memory_p, memory_v))
            zero = torch.zeros_like(kp)
            K = Mat2(kp, zero, zero, kv)
        a, b, c = a2, b2, c2
        out["xp"].append((p_pred, v_pred))
        out["x"].append((p, v))
        out["P"].append((a, b, c))
        out["Pp"].append((a1, b1, c1))
        out["e"].append((ep, ev))
        out["K"].append(K)

    def stacked(items: list[tuple[Tensor, ...]]) -> list[Tensor]:
        return [torch.stack(parts, dim=1) for parts in zip(*items, strict=True)]

    def full_time(x: Tensor) -> Tensor:
        return x.expand(B, steps, m) if x.ndim < 3 else x

    return AxisResult(
        mean=_pair(out["x"]),
        cov=Sym2(*stacked(out["P"])),
        pred_mean=_pair(out["xp"]),
        pred_cov=Sym2(*stacked(out["Pp"])),
        innovation=_pair(out["e"]),
        gain=Mat2(*stacked(out["K"])),
        observed=(seen_p, seen_v),
        noise=Sym2(*(full_time(x) for x in R_all)),
        interval=T_all,
        post_innovation=_pair(out["ep"]) if out["ep"] else None,
        log_likelihood=torch.stack(out["ll"], dim=1) if out["ll"] else None,
    )


def _pair(items: list[tuple[Tensor, Tensor]]) -> tuple[Tensor, Tensor]:
    return torch.stack([i[0] for i in items], dim=1), torch.stack([i[1] for i in items], dim=1)


def _later(x: Tensor) -> Tensor:
    """Steps ``1..T-1`` of a per-step tensor (unchanged when constant over time)."""
    return x[:, 1:] if x.ndim == 3 else x


class AxisBackward(NamedTuple):
    """The backward recursion's terms per axis at index ``k+1``, ``[B, T-1, m]`` (see
    :class:`~torchsvs.smoothers.rts.Backward`)."""

    C: Mat2
    d: tuple[Tensor, Tensor]
    GHF: Mat2
    GSG: Mat2
    GX: Mat2
    AF: Mat2


def backward_terms(res: AxisResult, projection: bool) -> AxisBackward:
    """``C, Γe, ΓHF, ΓSΓᵀ, ΓX, AF`` of :class:`~torchsvs.smoothers.RTSSmoother` per axis, with
    ``Γ = K`` (RTS) or, with ``projection``, ``Γ = P Hᵀ S⁻¹`` (SVSS, Eq. (42))."""
    Pp = full(Sym2(*(x[:, 1:] for x in res.pred_cov)))
    P = full(Sym2(*(x[:, :-1] for x in res.cov)))
    K = Mat2(*(x[:, 1:] for x in res.gain))
    R = full(Sym2(*(x[:, 1:] for x in res.noise)))
    fp, fv = (o[:, 1:].to(Pp.a.dtype) for o in res.observed)
    zero = torch.zeros_like(fp)
    H = Mat2(fp, zero, zero, fv)
    F = transition(_later(res.interval).expand_as(fp))
    PHt = mm(Pp, H)  # H is diagonal
    S = add(mm(H, PHt), R)
    Gamma = mm(PHt, full(inverse(Sym2(S.a, S.b, S.d)))) if projection else K
    A = Mat2(1 - K.a, -K.b, -K.c, 1 - K.d)  # I − K H (K has zero columns where H does)
    X = add(mm(t(PHt), t(A)), _neg(mm(R, t(K))))
    C = t(mm(full(inverse(Sym2(Pp.a, Pp.b, Pp.d))), mm(F, P)))  # P_{k|k} Fᵀ P_{k+1|k}⁻¹
    e = (res.innovation[0][:, 1:], res.innovation[1][:, 1:])
    return AxisBackward(
        C=C,
        d=mv(Gamma, e),
        GHF=mm(mm(Gamma, H), F),
        GSG=mm(mm(Gamma, S), t(Gamma)),
        GX=mm(Gamma, X),
        AF=mm(A, F),
    )


def _neg(X: Mat2) -> Mat2:
    return Mat2(-X.a, -X.b, -X.c, -X.d)


def _slice(X: Mat2, k: slice | int) -> Mat2:
    return Mat2(*(x[:, k] for x in X))


def _recurse(
    b: AxisBackward, g: tuple[Tensor, Tensor], G: Mat2, Z: Mat2, k: slice | int
) -> tuple[tuple[Tensor, Tensor], Mat2, Mat2]:
    """One application of the backward recursion at steps ``k`` given the terms at ``k+1``."""
    C = _slice(b.C, k)
    cross = mm(_slice(b.GX, k), t(G))
    d = (b.d[0][:, k], b.d[1][:, k])
    g_new = mv(C, (d[0] + g[0], d[1] + g[1]))
    G_new = mm(C, add(_slice(b.GHF, k), mm(G, _slice(b.AF, k))))
    inner = add(_slice(b.GSG, k), cross, t(cross), Z)
    Z_new = mm(mm(C, inner), t(C))
    return g_new, G_new, Z_new


def _rts_interval(res: AxisResult) -> tuple[tuple[Tensor, Tensor], Sym2]:
    """The fixed-interval RTS recursion, Eq. (17), Chen et al. 2020:
    ``x̂ˢ_k = x̂_k + C_k (x̂ˢ_{k+1} − x̂_{k+1|k})``, ``Pˢ_k = P_k + C_k (Pˢ_{k+1} − P_{k+1|k}) C_kᵀ``.
    With the filter's own gain as ``Γ`` this equals the general recursion of
    :class:`~torchsvs.smoothers.RTSSmoother` for any gain, in a third of the operations."""
    steps = res.mean[0].shape[1]
    interval = res.interval.expand_as(res.mean[0]) if res.interval.ndim else res.interval
    p_s, v_s = res.mean[0][:, -1], res.mean[1][:, -1]
    P_s = Sym2(*(x[:, -1] for x in res.cov))
    means, covs = [(p_s, v_s)], [P_s]
    for k in range(steps - 2, -1, -1):
        T = interval[:, k + 1] if interval.ndim else interval
        P = Sym2(*(x[:, k] for x in res.cov))
        Pp = Sym2(*(x[:, k + 1] for x in res.pred_cov))
        # C = P Fᵀ Pp⁻¹ with Fᵀ = [[1, 0], [T, 1]].
        PFt = Mat2(P.a + T * P.b, P.b, P.b + T * P.c, P.c)
        C = mm(PFt, full(inverse(Pp)))
        dp, dv = p_s - res.pred_mean[0][:, k + 1], v_s - res.pred_mean[1][:, k + 1]
        gp, gv = mv(C, (dp, dv))
        p_s, v_s = res.mean[0][:, k] + gp, res.mean[1][:, k] + gv
        D = sandwich(C, Mat2(P_s.a - Pp.a, P_s.b - Pp.b, P_s.b - Pp.b, P_s.c - Pp.c))
        P_s = Sym2(P.a + D.a, P.b + D.b, P.c + D.c)
        means.append((p_s, v_s))
        covs.append(P_s)
    means.reverse()
    covs.reverse()
    return _pair(means), Sym2(*(torch.stack(parts, dim=1) for parts in zip(*covs, strict=True)))


def smooth_axes(
    res: AxisResult, projection: bool, lag: int | None
) -> tuple[tuple[Tensor, Tensor], Sym2]:
    """Smoothed mean ``(p, v)`` and covariance per axis, ``[B, T, m]`` each (see
    :meth:`~torchsvs.smoothers.RTSSmoother.smooth`)."""
    steps = res.mean[0].shape[1]
    if steps == 1:
        return res.mean, res.cov
    if not projection and (lag is None or lag >= steps - 1):
        return _rts_interval(res)
    b = backward_terms(res, projection)
    zeros = torch.zeros_like(b.d[0])
    if lag is None or lag >= steps - 1:
        g: tuple[Tensor, Tensor] = (zeros[:, 0], zeros[:, 0])
        G = Mat2(*(zeros[:, 0],) * 4)
        Z = G
        out = []
        for k in range(steps - 2, -1, -1):
            g, G, Z = _recurse(b, g, G, Z, k)
            out.append((g, G, Z))
        out.reverse()
        g = (torch.stack([o[0][0] for o in out], 1), torch.stack([o[0][1] for o in out], 1))
        G = Mat2(*(torch.stack([o[1][i] for o in out], 1) for i in range(4)))
        Z = Mat2(*(torch.stack([o[2][i] for o in out], 1) for i in range(4)))
    else:
        g, G, Z = (zeros, zeros), Mat2(*(zeros,) * 4), Mat2(*(zeros,) * 4)

        def shift(x: Tensor) -> Tensor:
            return torch.cat([x[:, 1:], torch.zeros_like(x[:, :1])], dim=1)

        for _ in range(lag):
            g, G, Z = _recurse(
                b,
                (shift(g[0]), shift(g[1])),
                Mat2(*(shift(x) for x in G)),
                Mat2(*(shift(x) for x in Z)),
                slice(None),
            )
    P = full(Sym2(*(x[:, :-1] for x in res.cov)))
    PGt = mm(P, t(G))
    cov = add(P, _neg(PGt), _neg(t(PGt)), Z)
    head = Sym2(cov.a, 0.5 * (cov.b + cov.c), cov.d)
    mean = tuple(torch.cat([res.mean[i][:, :-1] + g[i], res.mean[i][:, -1:]], 1) for i in range(2))
    smoothed = Sym2(*(torch.cat([h, x[:, -1:]], 1) for h, x in zip(head, res.cov, strict=True)))
    return (mean[0], mean[1]), smoothed
