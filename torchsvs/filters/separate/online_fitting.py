r"""The online-fitting baseline of the separate-modeling tracker (Zhang & Zhou 2022, its ref.
[30]): a line in time per axis over a sliding window. A baseline the paper compares the tracker
with, not part of the tracker.

**Online fitting** (the paper's baseline, its ref. [30]): per axis, the first-degree polynomial
in time fitted by least squares to the latest ``k_m`` measurements; the estimate is the fit at
the newest time and the velocity its slope.

References:
    Zhang Zhuanhua, Zhou Gongjian, J. Syst. Eng. Electron. 33(5), 2022, its ref. [30].
"""

from __future__ import annotations

import torch
from torch import Tensor

from torchsvs.filters.separate.batch import batched


def sliding_windows(x: Tensor, length: int) -> tuple[Tensor, Tensor]:
    """The window of the latest ``length`` samples ending at every step.

    Args:
        x: ``[B, T, ...]``.
        length: window length ``L`` ≥ 1.

    Returns:
        ``windows [B, T, L, ...]`` (window ``t`` holds samples ``t − L + 1 .. t``, oldest first;
        0 before the first sample) and ``valid [B, T, L]`` (False before the first sample).
    """
    if not (isinstance(length, int) and length >= 1):
        raise ValueError(f"length: expected a positive integer, got {length!r}")
    if x.ndim < 2:
        raise ValueError(f"x: expected shape [B, T, ...], got {tuple(x.shape)}")
    B, T = x.shape[:2]
    padded = torch.cat([x.new_zeros(B, length - 1, *x.shape[2:]), x], dim=1)
    windows = padded.unfold(1, length, 1).movedim(-1, 2)
    index = torch.arange(T).unsqueeze(-1) - (length - 1) + torch.arange(length)
    valid = (index >= 0).expand(B, T, length)
    return windows, valid


def online_fit(z: Tensor, window: int, dt: float | Tensor = 1.0) -> Tensor:
    r"""The online-fitting baseline (the paper's ref. [30]): per axis and step, the line in time
    fitted by least squares to the latest ``window`` measurements, evaluated at the newest.

    With relative times :math:`\tau_j = t_j - t_k` of the valid samples ``j`` of the window
    ending at ``k``, their means :math:`\bar\tau`, :math:`\bar y`:

    .. math::
        \hat v_k = \frac{\sum_j (\tau_j - \bar\tau)(y_j - \bar y)}{\sum_j (\tau_j - \bar\tau)^2},
        \qquad \hat y_k = \bar y - \hat v_k\,\bar\tau.

    At the start of a track the window holds what exists (at least two samples); NaN components
    of ``z`` are left out of their axis's fit. Steps whose window holds fewer than two valid
    samples of an axis give NaN for it.

    Args:
        z: ``[B, T, d]`` position measurements (one track: ``[T, d]``).
        window: the window length ``k_m`` ≥ 2.
        dt: the sampling interval: a number or per step ``[B, T]`` (the interval ending at each
            step, as estimators take it; ``dt[:, 0]`` is not used).

    Returns:
        ``[B, T, 2d]``: per axis the position then the velocity (``[x, vx, y, vy]``, the layout
        of :class:`~torchsvs.models.ConstantVelocity`).
    """
    z, single = batched(z, "z", 3)
    B, T, d = z.shape
    if not (isinstance(window, int) and window >= 2):
        raise ValueError(f"window: expected an integer ≥ 2, got {window!r}")
    dt_t = torch.as_tensor(dt, dtype=z.dtype)
    if single and dt_t.ndim == 1:
        dt_t = dt_t.unsqueeze(0)
    if dt_t.ndim == 0:
        times = torch.arange(T, dtype=z.dtype).expand(B, T) * dt_t
    elif dt_t.shape == (B, T):
        times = torch.cat([dt_t.new_zeros(B, 1), dt_t[:, 1:].cumsum(1)], dim=1)
    else:
        raise ValueError(f"dt: expected a number or shape [{B}, {T}], got {tuple(dt_t.shape)}")
    if not bool(torch.isfinite(dt_t).all()) or bool((dt_t <= 0).any()):
        raise ValueError("dt: expected finite intervals > 0")
    zw, valid = sliding_windows(z, window)  # [B, T, L, d], [B, T, L]
    tw, _ = sliding_windows(times, window)
    tau = tw - times.unsqueeze(-1)  # [B, T, L], ≤ 0
    ok = valid.unsqueeze(-1) & torch.isfinite(zw)  # [B, T, L, d]
    w = ok.to(z.dtype)
    y = torch.where(ok, zw, torch.zeros_like(zw))
    tau = tau.unsqueeze(-1)
    count = w.sum(2)  # [B, T, d]
    safe_count = count.clamp_min(1.0)
    tau_bar = (w * tau).sum(2) / safe_count
    y_bar = (w * y).sum(2) / safe_count
    dtau = w * (tau - tau_bar.unsqueeze(2))
    s_tt = (dtau * dtau).sum(2)
    s_ty = (dtau * (y - y_bar.unsqueeze(2))).sum(2)
    fitted = (count >= 2) & (s_tt > 0)
    slope = s_ty / torch.where(fitted, s_tt, torch.ones_like(s_tt))
    value = y_bar - slope * tau_bar
    nan = torch.full_like(value, float("nan"))
    out = torch.stack([torch.where(fitted, value, nan), torch.where(fitted, slope, nan)], dim=-1)
    out = out.reshape(B, T, 2 * d)
    return out.squeeze(0) if single else out
