r"""Building blocks of the separate-modeling (SM) tracker of Zhang & Zhou (2022) and its
online-fitting baseline, as pure, batched, differentiable functions of tensors.

The SM tracker estimates a road target's mileage state and the straight line that approximates
its trajectory over a sliding window (the augmented model
:class:`~torchsvs.models.SeparateModel`, Eqs. (13)-(16)). Its cycle, per the paper's Sec. 4 and
Fig. 1: initialise the augmented state from the first three measurements by the unscented
transform (:func:`unscented_initialisation`, Eqs. (17)-(21)); then at every step ``k ≥ 4`` reset
the trajectory parameters by least squares over the window (:func:`reset_trajectory_parameters`,
Eqs. (36)-(40); not at the first cycle), mix (IMM interaction), filter each mode with an EKF,
update the mode probabilities and combine. The paper's equations were lost in extraction; what
follows rebuilds them from its text and the cited literature. Equation numbers are the paper's
where its text names them and inferred otherwise.

**Unscented initialisation.** The first three measurements :math:`z_1, z_2, z_3` are the only
information. The chord between adjacent measurements approximates the travelled distance, and
the base state follows by two-point differencing (Bar-Shalom et al. 2001, Sec. 5.5.3); the
window's line starts at the first measurement and points along the chord from the first to the
third. With :math:`d_{12} = \lVert z_2 - z_1\rVert`, :math:`d_{23} = \lVert z_3 - z_2\rVert`
and the intervals :math:`T_2, T_3` ending at samples 2 and 3, Eq. (19) (a reading):

.. math::
    s_3 = d_{12} + d_{23},\quad \dot s_3 = \frac{d_{23}}{T_3},\quad
    \ddot s_3 = \frac{d_{23}/T_3 - d_{12}/T_2}{T_3}\ \text{(NCA only; 0 for NCV)},

    (x_l, y_l) = z_1,\quad (r_x, r_y) = \frac{z_3 - z_1}{\lVert z_3 - z_1\rVert},\quad s_l = 0

(arc length counted from the first measurement). This map :math:`g` of the stacked measurements
:math:`Z = [z_1', z_2', z_3']'` (``n = 6``, covariance :math:`P_Z = \mathrm{diag}(R, R, R)`) is
pushed through the unscented transform (Julier & Uhlmann 1997), Eqs. (17)-(18):

.. math::
    \chi_0 = Z,\quad \chi_i = Z + \big(\sqrt{(n+\kappa)P_Z}\big)_i,\quad
    \chi_{i+n} = Z - \big(\sqrt{(n+\kappa)P_Z}\big)_i,

    W_0 = \frac{\kappa}{n+\kappa},\quad W_i = W_{i+n} = \frac{1}{2(n+\kappa)},\quad i = 1..n

(the columns of the lower Cholesky factor), then the covariance, Eq. (20), about the mean,
Eq. (21) (the text gives them in this order):

.. math::
    P^a_3 = \sum_{i=0}^{2n} W_i\, \big(g(\chi_i) - \hat{\mathbf x}^a_3\big)
    \big(g(\chi_i) - \hat{\mathbf x}^a_3\big)',\qquad
    \hat{\mathbf x}^a_3 = \sum_{i=0}^{2n} W_i\, g(\chi_i).

The NCV acceleration is identically 0, so its mean and every covariance element with it are 0,
as the paper says. The filter starts at ``k = 4``: in torchsvs' convention (the prior one step
before the first measurement) ``(x̂^a_3, P^a_3)`` is the prior of a run on ``z[:, 3:]``.
:math:`P^a_3` is singular (``s_l`` is exactly 0, the unit direction has one degree of freedom,
and six noise components drive eight states), so a torchsvs filter, which requires a positive
definite prior, needs ``floor > 0``.

**Least-squares reset.** At the cycle of measurement :math:`z_{k_2}` the window is
:math:`[k_1, k_2]` of the latest :math:`k_m` samples; the parameters estimated at
:math:`k_2 - 1` belong to the previous window, so they are recomputed from the window's
measurements except the new one, :math:`j = k_1..k_2-1`, with their estimated arc lengths
:math:`\hat s_j` and :math:`s_l = \hat s_{k_1}`. The cost :math:`J = \sum_j \lVert z_j -
h(\hat s_j, \eta)\rVert^2` (Eq. (35), inferred) separates into the two of Eq. (36):

.. math::
    J_x = \sum_{j=k_1}^{k_2-1} \big(x_j - x_l - r_x(\hat s_j - s_l)\big)^2,\qquad
    J_y = \sum_{j=k_1}^{k_2-1} \big(y_j - y_l - r_y(\hat s_j - s_l)\big)^2.

With :math:`V = [\mathbf 1,\ \hat{\mathbf s} - s_l]` and its QR decomposition
:math:`V = UG`, :math:`U'U = I`, :math:`G` upper triangular (Eqs. (37)-(38), inferred), the
normal equations :math:`V'V\theta = V'\mathbf x` become :math:`G\theta = U'\mathbf x`:

.. math::
    [x_l^*, r_x^*]' = G^{-1}U'\mathbf x,\qquad [y_l^*, r_y^*]' = G^{-1}U'\mathbf y
    \quad \text{(Eq. (39), inferred)},

and the parameter vector is reset to :math:`\eta^* = [x_l^*, r_x^*, y_l^*, r_y^*, s_l]'`
(Eq. (40), inferred). The line of Eq. (13) is the natural (arc-length) parameterisation, so
the direction is a unit vector; the unconstrained LS slope has norm 1 only when the estimated
arc lengths are exact. This implementation normalises it, :math:`(r_x^*, r_y^*) \leftarrow
(r_x^*, r_y^*) / \lVert(r_x^*, r_y^*)\rVert`, and keeps the LS intercept (``normalize=False``
keeps the raw LS solution): the window's scale error then shows in the innovations, where the
filter corrects the arc length, instead of being absorbed in the direction.

**Online fitting** (the paper's baseline, its ref. [30]): per axis, the first-degree polynomial
in time fitted by least squares to the latest ``k_m`` measurements; the estimate is the fit at
the newest time and the velocity its slope.

References:
    Zhang Zhuanhua, Zhou Gongjian, J. Syst. Eng. Electron. 33(5), 2022, Sec. 4 · Julier,
    Uhlmann, "A new extension of the Kalman filter to nonlinear systems", Proc. SPIE 3068, 1997.
    doi:10.1117/12.280797 · Bar-Shalom, Li, Kirubarajan, "Estimation with Applications to
    Tracking and Navigation", Wiley 2001.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.models.mileage import SeparateModel

#: Measurements the initialisation uses (the filter starts at the fourth).
INITIAL_SAMPLES = 3


class AugmentedPrior(NamedTuple):
    """The unscented initialisation of the augmented state, ``x̂^a_{3|3}`` and ``P^a_{3|3}``."""

    mean: Tensor  #: [B, n]
    cov: Tensor  #: [B, n, n]


def _batched(x: Tensor, name: str, rank: int) -> tuple[Tensor, bool]:
    """``x`` with a batch axis (added for one track of rank ``rank - 1``) and whether added."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a tensor, got {type(x).__name__}")
    if not x.is_floating_point():
        raise TypeError(f"{name}: expected a floating-point tensor, got {x.dtype}")
    if x.ndim == rank - 1:
        return x.unsqueeze(0), True
    if x.ndim != rank:
        raise ValueError(
            f"{name}: expected rank {rank} (or {rank - 1} for one track), got {x.ndim}"
        )
    return x, False


def _intervals(model: SeparateModel, dt: float | Tensor | None, like: Tensor) -> Tensor:
    """``[B, 2]``: the intervals ending at samples 2 and 3."""
    B = like.shape[0]
    if dt is None:
        dt = model.dt
    d = torch.as_tensor(dt, dtype=like.dtype)
    if d.ndim == 0:
        d = d.expand(B, 2)
    elif d.ndim == 1 and d.shape[0] == B:
        d = d.unsqueeze(-1).expand(B, 2)
    elif d.ndim == 2 and d.shape[0] == B and d.shape[1] >= INITIAL_SAMPLES:
        d = d[:, 1:INITIAL_SAMPLES]
    else:
        raise ValueError(
            f"dt: expected a scalar, per track [{B}] or per step [{B}, T ≥ 3], got {tuple(d.shape)}"
        )
    if not bool(torch.isfinite(d).all()) or bool((d <= 0).any()):
        raise ValueError("dt: expected finite intervals > 0")
    return d


def three_point_state(model: SeparateModel, z: Tensor, dt: float | Tensor | None = None) -> Tensor:
    r"""The augmented state ``[..., n]`` from three position measurements, Eq. (19) (module
    docstring): chord-length arc length, two-point-differenced speed, the second difference as
    NCA acceleration (0 for NCV), the line from :math:`z_1` along :math:`z_3 - z_1`.

    Args:
        model: the augmented model (its layout, and its ``dt`` when ``dt`` is None).
        z: ``[B, 3, 2]`` (or ``[B, T ≥ 3, 2]``: the first three are used), or one track
            ``[3, 2]``.
        dt: the sampling interval: a number, per track ``[B]`` or per step ``[B, T]``.
    """
    z, single = _batched(z, "z", 3)
    if z.shape[1] < INITIAL_SAMPLES or z.shape[2] != 2:
        raise ValueError(f"z: expected shape [B, T ≥ 3, 2], got {tuple(z.shape)}")
    T = _intervals(model, dt, z)
    x = _three_point(z[:, :INITIAL_SAMPLES].reshape(z.shape[0], 6), T, model)
    return x.squeeze(0) if single else x


def _three_point(Z: Tensor, T: Tensor, model: SeparateModel) -> Tensor:
    """Eq. (19) on stacked measurements ``Z [B, 6]`` with intervals ``T [B, 2]``."""
    z1, z2, z3 = Z[:, 0:2], Z[:, 2:4], Z[:, 4:6]
    d12, d23 = (z2 - z1).norm(dim=-1), (z3 - z2).norm(dim=-1)
    chord = z3 - z1
    direction = chord / chord.norm(dim=-1, keepdim=True)
    speed = d23 / T[:, 1]
    base = [d12 + d23, speed]
    if model.has_acceleration:
        accel = (speed - d12 / T[:, 0]) / T[:, 1]
        base.append(accel if model.base_order == 3 else torch.zeros_like(accel))
    eta = [z1[:, 0], direction[:, 0], z1[:, 1], direction[:, 1], torch.zeros_like(speed)]
    return torch.stack(base + eta, dim=-1)


def unscented_initialisation(
    model: SeparateModel,
    z: Tensor,
    dt: float | Tensor | None = None,
    R: Tensor | None = None,
    kappa: float = 0.0,
    floor: float = 0.0,
) -> AugmentedPrior:
    r"""Mean and covariance of the augmented state after the first three measurements by the
    unscented transform of their noise, Eqs. (17)-(21) (module docstring).

    Args:
        model: the augmented model (layout; ``dt`` and ``R`` when not given).
        z: ``[B, T ≥ 3, 2]`` measurements (the first three are used) or one track ``[T, 2]``.
        dt: the sampling interval: a number, per track ``[B]`` or per step ``[B, T]`` (the
            intervals ending at samples 2 and 3 are used).
        R: the measurement noise covariance ``[2, 2]`` or per track ``[B, 2, 2]``; default the
            model's.
        kappa: the unscented transform's ``κ``, ``n + κ > 0`` with ``n = 6`` (default 0: equal
            weights ``1/12``, a positive semi-definite covariance; Julier & Uhlmann's
            ``n + κ = 3`` gives ``κ = −3`` and a negative centre weight).
        floor: variance added to every diagonal element of the covariance (> 0 makes it
            positive definite, as torchsvs' filters require of a prior).

    Returns:
        :class:`AugmentedPrior` ``(mean [B, n], cov [B, n, n])`` (no batch axis for one track):
        the prior of a filter run on ``z[:, 3:]``.
    """
    z, single = _batched(z, "z", 3)
    B = z.shape[0]
    if z.shape[1] < INITIAL_SAMPLES or z.shape[2] != 2:
        raise ValueError(f"z: expected shape [B, T ≥ 3, 2], got {tuple(z.shape)}")
    first = z[:, :INITIAL_SAMPLES]
    if not bool(torch.isfinite(first).all()):
        raise ValueError("z: the first three measurements must be finite (no missing values)")
    n = 2 * INITIAL_SAMPLES
    if not n + kappa > 0:
        raise ValueError(f"kappa: expected n + κ > 0 with n = {n}, got κ = {kappa!r}")
    if not floor >= 0:
        raise ValueError(f"floor: expected a number ≥ 0, got {floor!r}")
    T = _intervals(model, dt, z)
    R_t = (model.meas_cov() if R is None else R).to(z.dtype)
    if R_t.shape not in ((2, 2), (B, 2, 2)):
        raise ValueError(f"R: expected shape [2, 2] or [{B}, 2, 2], got {tuple(R_t.shape)}")
    P_Z = torch.block_diag(*[R_t] * INITIAL_SAMPLES) if R_t.ndim == 2 else _block_diag3(R_t)
    L = torch.linalg.cholesky((n + kappa) * P_Z).expand(B, n, n)
    Z = first.reshape(B, n)
    spread = L.mT  # rows are the columns of L
    sigma = torch.cat([Z.unsqueeze(1), Z.unsqueeze(1) + spread, Z.unsqueeze(1) - spread], dim=1)
    image = _three_point(
        sigma.reshape(-1, n), T.repeat_interleave(2 * n + 1, dim=0), model
    ).reshape(B, 2 * n + 1, -1)
    weights = torch.full((2 * n + 1,), 0.5 / (n + kappa), dtype=z.dtype)
    weights[0] = kappa / (n + kappa)
    mean = torch.einsum("s,bsi->bi", weights, image)
    dev = image - mean.unsqueeze(1)
    cov = torch.einsum("s,bsi,bsj->bij", weights, dev, dev)
    cov = (cov + cov.mT) / 2.0
    if floor > 0:
        cov = cov + floor * torch.eye(cov.shape[-1], dtype=cov.dtype)
    if single:
        return AugmentedPrior(mean.squeeze(0), cov.squeeze(0))
    return AugmentedPrior(mean, cov)


def _block_diag3(R: Tensor) -> Tensor:
    """``diag(R, R, R)`` per track from ``R [B, 2, 2]``: ``[B, 6, 6]``."""
    eye = torch.eye(INITIAL_SAMPLES, dtype=R.dtype)
    return torch.einsum("ij,bkl->bikjl", eye, R).reshape(R.shape[0], 6, 6)


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


def reset_trajectory_parameters(
    positions: Tensor,
    arc_length: Tensor,
    mask: Tensor | None = None,
    normalize: bool = True,
) -> Tensor:
    r"""The least-squares reset of the trajectory parameters over a window, Eqs. (36)-(40):
    :math:`\eta^* = [x_l^*, r_x^*, y_l^*, r_y^*, s_l]` (module docstring).

    Args:
        positions: the window's measurements ``[B, W, 2]`` (one track: ``[W, 2]``), oldest
            first: the latest ``k_m`` except the newest. NaN marks a missing one.
        arc_length: their estimated arc lengths ``ŝ_j``, ``[B, W]``.
        mask: ``[B, W]``, True for the samples that belong to the window (a window shorter than
            ``W`` at the start of a track); default all.
        normalize: scale the LS direction to unit length (default; keeps the LS intercept).

    Returns:
        ``η* [B, 5]`` with ``s_l`` the first valid arc length of each window; NaN for a window
        with fewer than two valid samples or without two distinct arc lengths.
    """
    positions, single = _batched(positions, "positions", 3)
    arc_length, _ = _batched(arc_length, "arc_length", 2)
    B, W = positions.shape[:2]
    if positions.shape[2] != 2 or W < 2:
        raise ValueError(f"positions: expected shape [B, W ≥ 2, 2], got {tuple(positions.shape)}")
    if arc_length.shape != (B, W):
        raise ValueError(f"arc_length: expected shape [{B}, {W}], got {tuple(arc_length.shape)}")
    valid = torch.isfinite(positions).all(-1) & torch.isfinite(arc_length)
    if mask is not None:
        mask = mask.unsqueeze(0) if single and mask.ndim == 1 else mask
        if mask.shape != (B, W) or mask.dtype != torch.bool:
            raise ValueError(f"mask: expected a bool tensor [{B}, {W}], got {tuple(mask.shape)}")
        valid = valid & mask
    first = valid.to(torch.uint8).argmax(dim=1, keepdim=True)  # first valid sample
    s = torch.where(valid, arc_length, torch.zeros_like(arc_length))
    s_l = s.gather(1, first).squeeze(1)
    offset = torch.where(valid, arc_length - s_l.unsqueeze(1), torch.zeros_like(arc_length))
    w = valid.to(positions.dtype)
    V = torch.stack([w, offset], dim=-1)  # [B, W, 2], Eq. (37)
    b = torch.where(valid.unsqueeze(-1), positions, torch.zeros_like(positions))
    spread = torch.where(valid, arc_length, s_l.unsqueeze(1))
    solvable = (valid.sum(1) >= 2) & (spread.amax(1) > spread.amin(1))
    # An unsolvable window gets a harmless full-rank problem (its result is replaced by NaN), so
    # no NaN enters the graph of the others' gradients.
    harmless = torch.eye(W, 2, dtype=V.dtype)
    V = torch.where(solvable[:, None, None], V, harmless)
    b = torch.where(solvable[:, None, None], b, harmless.sum(-1, keepdim=True).expand(W, 2))
    U, G = torch.linalg.qr(V)  # Eq. (38)
    theta = torch.linalg.solve_triangular(G, U.mT @ b, upper=True)  # [B, 2, 2], Eq. (39)
    start, direction = theta[:, 0], theta[:, 1]
    if normalize:
        direction = direction / direction.norm(dim=-1, keepdim=True)
    eta = torch.stack([start[:, 0], direction[:, 0], start[:, 1], direction[:, 1], s_l], dim=-1)
    eta = torch.where(solvable.unsqueeze(-1), eta, torch.full_like(eta, float("nan")))
    return eta.squeeze(0) if single else eta


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
    z, single = _batched(z, "z", 3)
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
