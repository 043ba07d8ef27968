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
arc lengths are exact. :func:`reset_trajectory_parameters` can normalise it,
:math:`(r_x^*, r_y^*) \leftarrow (r_x^*, r_y^*) / \rho`, :math:`\rho = \lVert(r_x^*,
r_y^*)\rVert`, keeping the LS intercept (``normalize=True``, its default), or return the raw
LS solution, as the paper's text resets (``normalize=False``). The norm :math:`\rho` is the
window's verdict on the scale of the estimated arc lengths (the fitted positions are
:math:`x_l^* + \rho\,u\,(\hat s_j - s_l)`: the target travelled :math:`\rho` times the
estimated distance); normalising alone discards it, keeping the raw slope lets the mileage
unit drift by it (see :class:`SeparateModelingTracker`, which by default moves it into the
mileage state instead).

**The reset's covariance** (not in the paper's text): per axis the LS problem is
:math:`V\theta = \mathbf x` with noise of covariance :math:`R` between the axes, so
:math:`\mathrm{Cov}([x_l^*, r_x^*, y_l^*, r_y^*]') = \tilde R\otimes(V'V)^{-1}`,
:math:`(V'V)^{-1} = G^{-1}G^{-\prime}`, carried through a normalisation's Jacobian
:math:`(I - uu')/\rho` (:func:`reset_covariance`); :math:`\tilde R` is :math:`R` or the
window's residual covariance pooled with it. :class:`SeparateModelingTracker` sets ``η``'s
block to it at each reset (its docstring says why).

**The tracker**, :class:`SeparateModelingTracker`, is the :class:`~torchsvs.IMM` of the
NCV and NCA augmented models with these blocks in its interaction hooks; the acceleration the
NCV mode lacks is mixed without bias (its docstring).

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

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.constraints import ArrayLike
from torchsvs.estimator import check_keep, drop_batch, prepare_inputs, threads_for
from torchsvs.filters.imm import IMM, IMMResult, IMMState
from torchsvs.filters.nonlinear import ExtendedKalmanFilter, UnscentedKalmanFilter
from torchsvs.kernels.compiled import outside_dynamo
from torchsvs.models.mileage import (
    MileageConstantAcceleration,
    MileageConstantVelocity,
    SeparateModel,
)
from torchsvs.types import FilterState

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


class LineFit(NamedTuple):
    """The least-squares line of a window (:func:`fit_window_line`), per track."""

    start: Tensor  #: [B, 2] the intercept (x_l*, y_l*), Eq. (39)
    slope: Tensor  #: [B, 2] the LS direction (r_x*, r_y*) before any normalisation
    s_l: Tensor  #: [B] the window's start arc length (first valid sample)
    offset: Tensor  #: [B, W] ŝ_j − s_l of the valid samples (0 elsewhere)
    valid: Tensor  #: [B, W] the samples that entered the fit
    gram_inverse: Tensor  #: [B, 2, 2] (V'V)⁻¹ = G⁻¹G⁻ᵀ
    solvable: Tensor  #: [B] at least two valid samples at distinct arc lengths


def fit_window_line(positions: Tensor, arc_length: Tensor, mask: Tensor | None = None) -> LineFit:
    """The QR least-squares fit of Eqs. (36)-(39) over each window (module docstring), with
    what its covariance needs. Arguments as for :func:`reset_trajectory_parameters` (batched:
    ``positions [B, W, 2]``, ``arc_length [B, W]``); an unsolvable window's entries are
    finite and meaningless (``solvable`` is False)."""
    B, W = positions.shape[:2]
    valid = torch.isfinite(positions).all(-1) & torch.isfinite(arc_length)
    if mask is not None:
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
    eye = torch.eye(2, dtype=G.dtype).expand_as(G)
    G_inv = torch.linalg.solve_triangular(G, eye, upper=True)
    return LineFit(theta[:, 0], theta[:, 1], s_l, offset, valid, G_inv @ G_inv.mT, solvable)


def _checked_window(
    positions: Tensor, arc_length: Tensor, mask: Tensor | None
) -> tuple[Tensor, Tensor, Tensor | None, bool]:
    positions, single = _batched(positions, "positions", 3)
    arc_length, _ = _batched(arc_length, "arc_length", 2)
    B, W = positions.shape[:2]
    if positions.shape[2] != 2 or W < 2:
        raise ValueError(f"positions: expected shape [B, W ≥ 2, 2], got {tuple(positions.shape)}")
    if arc_length.shape != (B, W):
        raise ValueError(f"arc_length: expected shape [{B}, {W}], got {tuple(arc_length.shape)}")
    if mask is not None:
        mask = mask.unsqueeze(0) if single and mask.ndim == 1 else mask
        if mask.shape != (B, W) or mask.dtype != torch.bool:
            raise ValueError(f"mask: expected a bool tensor [{B}, {W}], got {tuple(mask.shape)}")
    return positions, arc_length, mask, single


def _eta(fit: LineFit, normalize: bool) -> Tensor:
    """``η* [B, 5]`` of a fit, NaN where unsolvable."""
    start, direction = fit.start, fit.slope
    if normalize:
        direction = direction / direction.norm(dim=-1, keepdim=True)
    eta = torch.stack([start[:, 0], direction[:, 0], start[:, 1], direction[:, 1], fit.s_l], dim=-1)
    return torch.where(fit.solvable.unsqueeze(-1), eta, torch.full_like(eta, float("nan")))


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
    positions, arc_length, mask, single = _checked_window(positions, arc_length, mask)
    eta = _eta(fit_window_line(positions, arc_length, mask), normalize)
    return eta.squeeze(0) if single else eta


#: Weight, in residuals, of the sensor noise ``R`` in the residual estimate of the reset's
#: covariance (:func:`reset_covariance`).
PRIOR_RESIDUALS = 2.0


def _reset_covariance(
    fit: LineFit, positions: Tensor, R: Tensor, normalize: bool, residual: bool
) -> Tensor:
    """:func:`reset_covariance` of a fit ``[B, 5, 5]``."""
    B = positions.shape[0]
    noise = R.to(positions.dtype).expand(B, 2, 2)
    if residual:
        fitted = fit.start.unsqueeze(1) + fit.offset.unsqueeze(-1) * fit.slope.unsqueeze(1)
        e = torch.where(fit.valid.unsqueeze(-1), positions - fitted, torch.zeros_like(positions))
        count = fit.valid.sum(1).to(positions.dtype)
        noise = (e.mT @ e + PRIOR_RESIDUALS * noise) / (count - 2.0 + PRIOR_RESIDUALS).clamp_min(
            PRIOR_RESIDUALS
        )[:, None, None]
    # Cov([x_l, r_x, y_l, r_y]) = R̃ ⊗ (V'V)⁻¹ (axis-major order).
    theta = torch.einsum("bij,bkl->bikjl", noise, fit.gram_inverse).reshape(B, 4, 4)
    if normalize:
        rho = fit.slope.norm(dim=-1).clamp_min(torch.finfo(positions.dtype).tiny)
        u = fit.slope / rho.unsqueeze(-1)
        tangent = (torch.eye(2, dtype=u.dtype) - u.unsqueeze(-1) * u.unsqueeze(-2)) / rho[
            :, None, None
        ]
        J = torch.zeros(B, 4, 4, dtype=u.dtype)
        J[:, 0, 0] = J[:, 2, 2] = 1.0
        J[:, 1::2, 1::2] = tangent
        theta = J @ theta @ J.mT
    cov = positions.new_zeros(B, 5, 5)
    cov[:, :4, :4] = (theta + theta.mT) / 2
    return cov


def reset_covariance(
    positions: Tensor,
    arc_length: Tensor,
    R: Tensor,
    mask: Tensor | None = None,
    normalize: bool = True,
    residual: bool = True,
) -> Tensor:
    r"""The covariance ``[B, 5, 5]`` of the least-squares parameters
    :math:`\eta^*` of :func:`reset_trajectory_parameters`, as the SM tracker sets it at a
    reset (module docstring).

    Per axis the LS problem is ``V θ = x`` with noise of covariance ``R`` between the axes, so
    :math:`\mathrm{Cov}([x_l, r_x, y_l, r_y]) = \tilde R \otimes (V'V)^{-1}` with
    :math:`(V'V)^{-1} = G^{-1}G^{-\prime}` from the QR factor; :math:`\tilde R` is ``R``
    (``residual=False``) or the residuals' covariance pooled with ``R`` worth
    :data:`PRIOR_RESIDUALS` residuals, :math:`\tilde R = (E'E + 2R)/(N - 2 + 2)` (a window
    the line does not fit, a bend, widens it). The normalised direction
    :math:`u = r/\rho` takes the Jacobian :math:`(I - uu')/\rho`; ``s_l`` is the window's
    anchor, a chosen number: variance 0. Gives zeros for an unsolvable window.

    Args:
        positions, arc_length, mask, normalize: as for :func:`reset_trajectory_parameters`.
        R: the measurement noise covariance ``[2, 2]`` or ``[B, 2, 2]``.
        residual: pool the residuals into the noise estimate (default) or use ``R`` alone.
    """
    positions, arc_length, mask, single = _checked_window(positions, arc_length, mask)
    fit = fit_window_line(positions, arc_length, mask)
    cov = _reset_covariance(fit, positions, R, normalize, residual)
    cov = torch.where(fit.solvable[:, None, None], cov, torch.zeros_like(cov))
    return cov.squeeze(0) if single else cov


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


# --- The SM tracker ------------------------------------------------------------------------------

#: The mode transition matrix of the SM tracker and its Cartesian IMM baselines (the paper's
#: matrices were lost in extraction): a standard choice, 5% switching per step.
DEFAULT_TRANSITION = ((0.95, 0.05), (0.05, 0.95))


#: Where the NCV mode's ``[s, ṡ, η]`` and the NCA mode's ``[s, ṡ, s̈, η]`` sit in the
#: tracker's common state ``[s, ṡ, s̈, x_l, r_x, y_l, r_y, s_l]`` (the
#: :class:`~torchsvs.IMM`'s ``embedding`` with the default ``mixing="unbiased"`` of
#: :class:`SeparateModelingTracker`: the NCV mode has no acceleration to mix).
MODE_EMBEDDING = ((0, 1, 3, 4, 5, 6, 7), (0, 1, 2, 3, 4, 5, 6, 7))
#: How the SM tracker mixes the acceleration the NCV mode lacks (:class:`SeparateModelingTracker`).
MIXINGS = ("unbiased", "zero")


#: What the SM tracker does to ``η``'s covariance at a reset (:class:`SeparateModelingTracker`).
RESET_COVARIANCES = ("residual", "measurement", "keep")
#: What the SM tracker does with the norm of the LS direction (:class:`SeparateModelingTracker`).
RESET_DIRECTIONS = ("rescale", "normalize", "raw")


class ResetWindow(NamedTuple):
    """What the least-squares reset keeps of earlier steps (``IMMState.aux`` of
    :class:`SeparateModelingTracker`): the latest ``k_m − 1`` measurements and their estimated
    arc lengths, oldest first.

    Attributes:
        z: ``[B, W, 2]`` measurements, NaN where missing or before the track started.
        arc_length: ``[B, W]`` their estimated arc lengths ``ŝ_{j|j}``; NaN for the newest until
            the next cycle fills it in (the estimate after the newest step is in the state).
    """

    z: Tensor
    arc_length: Tensor


class SeparateModelingResult(NamedTuple):
    """What a :class:`SeparateModelingTracker` pass produced (``B`` tracks, ``T`` steps).

    Steps ``0..2`` (the paper's ``k = 1..3``) are the unscented initialisation when the
    tracker initialised itself (``x0=None``): see :class:`SeparateModelingTracker`.

    Attributes:
        cartesian: ``[B, T, 4]`` Cartesian estimate ``[x, vx, y, vy]`` (the layout of
            :class:`~torchsvs.models.ConstantVelocity`): per mode the position
            :math:`h(\\hat x^j)` and the velocity :math:`\\hat{\\dot s}^j\\,(\\hat r_x^j,
            \\hat r_y^j)`, combined with the mode probabilities.
        mean: ``[B, T, 8]`` combined augmented state ``[s, ṡ, s̈, x_l, r_x, y_l, r_y, s_l]``.
        cov: ``[B, T, 8, 8]`` its covariance (``None`` with ``keep="mean"``).
        mode_probs: ``[B, T, 2]`` probabilities of the NCV and NCA modes.
        imm: the :class:`~torchsvs.filters.imm.IMMResult` of the filtered steps (``z[:, 3:]``
            after a self-initialisation, else every step), per-mode results included, each in
            its mode's own state (the NCV mode's ``[s, ṡ, η]``, the NCA mode's
            ``[s, ṡ, s̈, η]``; :attr:`SeparateModelingTracker.mode_models`).
        log_likelihood: ``[B]``, the IMM's, over the filtered steps.
    """

    cartesian: Tensor
    mean: Tensor
    cov: Tensor | None
    mode_probs: Tensor
    imm: IMMResult
    log_likelihood: Tensor | None = None

    @property
    def mileage(self) -> Tensor:
        """``[B, T, 3]`` the mileage state ``[s, ṡ, s̈]`` (in units of the line's parameter:
        arc length times ``‖r‖`` when the reset keeps the raw LS direction)."""
        return self.mean[..., :3]

    @property
    def eta(self) -> Tensor:
        """``[B, T, 5]`` the trajectory parameters ``η = [x_l, r_x, y_l, r_y, s_l]``."""
        return self.mean[..., 3:]


class SeparateModelingTracker(IMM):
    r"""The separate-modeling (SM) tracker of Zhang & Zhou (2022): an NCV-NCA IMM in mileage
    coordinates on the augmented models :class:`~torchsvs.models.SeparateModel`, whose
    trajectory parameters ``η`` are reset by least squares before every interaction stage
    except the first.

    Modes: NCV (:class:`~torchsvs.models.MileageConstantVelocity`, state ``[s, ṡ, η]``) and
    NCA (:class:`~torchsvs.models.MileageConstantAcceleration`, ``[s, ṡ, s̈, η]``), both
    augmented by :math:`\eta = [x_l, r_x, y_l, r_y, s_l]`. The estimate lives in the common
    state ``[s, ṡ, s̈, x_l, r_x, y_l, r_y, s_l]`` (the IMM's ``embedding``,
    :data:`MODE_EMBEDDING`), where the NCV mode's acceleration counts as 0 with variance 0 in
    the combination (the paper's Sec. 4: "for the NCV model, the acceleration component ... is
    zero and the elements related to the acceleration in the covariance are zero"); how the
    missing acceleration is mixed: see below. Each mode is filtered by an
    :class:`~torchsvs.ExtendedKalmanFilter` (the paper's choice) or, with ``unscented=True``,
    an :class:`~torchsvs.UnscentedKalmanFilter`.

    One cycle at sample ``k`` (the paper's Fig. 1):

    1. **Initialisation** (once, :meth:`initialise`): the unscented transform of the first three
       measurements (:func:`unscented_initialisation`, Eqs. (17)-(21)) gives each mode's
       ``x̂^a_{3|3}``, ``P^a_{3|3}`` (plus ``floor`` on the diagonal: the transform's covariance
       is singular); the filter starts at ``k = 4``.
    2. **Reset** (:meth:`adjust_modes`, at every cycle except the first): the window is the
       latest ``k_m = window`` samples ``k − k_m + 1 .. k``; its measurements except the newest,
       with the arc lengths estimated at their own steps (:math:`\hat s_{j|j}`, the IMM's
       combined estimate), give :math:`\eta^*` by the QR least squares of
       :func:`reset_trajectory_parameters` (Eqs. (36)-(40); ``s_l = ŝ_{k_1}``). Every mode's
       ``η`` mean is set to :math:`\eta^*` (its direction and covariance: see below); the base
       state (``s, ṡ, s̈``) keeps its latest update, rescaled by the fit (below). A window with
       fewer than two usable samples (missing measurements) keeps the filter's ``η``.
    3. **Interaction, mode-matched filtering, mode probabilities, combination**: the
       :class:`~torchsvs.IMM`'s.

    **Mixing the acceleration the NCV mode lacks** (``mixing``). When the NCA mode's initial
    condition is mixed, the NCV mode has no ``s̈`` to contribute. Padding its state with
    ``s̈ = 0`` of variance 0 (``"zero"``: the NCV model embedded in the NCA layout,
    ``SeparateModel(..., embed_acceleration=True)``, every mode in one state) turns the mixing
    into a shrinkage of the NCA acceleration: with :math:`\mu_{i|j}` the mixing probabilities,
    :math:`\hat{\ddot s}^{0,NCA} = \mu_{NCA|NCA}\,\hat{\ddot s}^{NCA}`, and its variance and
    its covariances with ``s``, ``ṡ`` shrink by the same factor (plus the spread of the two
    means), at every step. The zero is not an estimate of the target's acceleration but the
    absence of one, so this mixing is biased (Yuan et al. 2012; Granström et al. 2015). With
    the paper's small ``q`` (the NCA acceleration may change by ``q`` per step) the bias
    decides the result: whenever the NCV mode is probable the NCA mode's acceleration and its
    variance are pulled to 0 step after step, so when an acceleration starts the NCA mode
    cannot build up ``s̈``, the speed lags, and only the reset's slope norm (``ρ``, below) drags
    it along. The default (``"unbiased"``) mixes as :class:`~torchsvs.IMM` does modes of
    unequal state (and as the Cartesian IMM-KF(CVCA) the paper compares with is run in
    ``experiments/road_tracking.py``): mixing into the NCA mode, the NCV mode lends the NCA
    mode's own ``s̈`` mean and variance, uncorrelated with its ``s``, ``ṡ``, ``η``, so only the
    NCA mode's own filter changes its acceleration, while ``s``, ``ṡ`` and ``η`` mix with the
    spread of the modes' means as usual. The price: an NCA acceleration that is wrong (the
    spurious one the initialisation's chord-length speed leaves for a slow target, whose
    chords are mostly noise) is corrected by the NCA mode's own filter alone, slowly at a
    small ``q``, where the zero padding would shrink it away. The experiment compares the two
    (ablation).

    **The reset's direction** (``direction``). The LS slope :math:`r^* = \rho u` has norm
    :math:`\rho \ne 1` when the estimated arc lengths of the window are off in scale (a speed
    that lags an acceleration: the target travelled :math:`\rho` times the estimated
    distance). The paper's text resets to the LS solution (``"raw"``): the positions and
    velocities ``ṡ r`` are then right, but the unit of the mileage drifts by every
    :math:`\rho` (``‖r‖`` wanders far from 1; ``q`` acts on ``s`` in that drifting unit, so
    it stands for a larger noise in metres). Normalising ``r`` alone (``"normalize"``) keeps
    the natural parameterisation but discards :math:`\rho`, and the tracker lags the
    accelerations more. By default (``"rescale"``) the direction is normalised and
    :math:`\rho` moves into the mileage state, an exact reparameterisation of the raw reset's
    mean: :math:`s \leftarrow s_l + \rho(s - s_l)`, :math:`\dot s \leftarrow \rho\dot s`,
    :math:`\ddot s \leftarrow \rho\ddot s` (their covariance by the same factor; the window's
    arc lengths too), so the mileage stays in metres, ``r`` a unit vector and ``q`` in m/s².
    :math:`\rho` is taken as exact: its variance (the least-squares slope's along its
    direction) is left out, as the normalised direction's covariance leaves it out.
    ``experiments/road_tracking.py`` compares the three.

    **η's covariance at a reset** (``reset_covariance``). The paper resets "the parameter
    vector" and says nothing of its covariance (its equation for the updated covariance was
    lost). Keeping the filter's covariance for the moved mean (``"keep"``) is inconsistent:
    with the tiny artificial noise ``σ_η`` the filter's ``η`` covariance shrinks without bound,
    while every reset moves ``η`` by far more than it allows (``s_l`` by a step's travel, ``x_l``
    with it); the EKF then puts each innovation into the arc length, and the tracker is less
    accurate, most on the bends. By default the reset sets ``η``'s block to the covariance of
    the least-squares estimate itself (:func:`reset_covariance`: :math:`\tilde R \otimes
    (V'V)^{-1}`, through a normalisation's Jacobian, ``s_l`` an anchor of variance 0, plus
    ``floor``), with the noise :math:`\tilde R` estimated from the window's residuals pooled
    with ``R`` (``"residual"``: a window the line does not fit, on a bend, gets a wider
    covariance, so the new measurement counts more) or ``R`` alone (``"measurement"``), and
    zeroes ``η``'s cross-covariance with the base state: the reset is a re-initialisation of
    the line, and its dependence on the filter's earlier arc lengths is ignored, as in any
    reset. The base block is the filter's. ``experiments/road_tracking.py`` compares the three.

    **Orientation.** ``(s, ṡ, s̈, r, s_l)`` and its negative give the same measurement function
    and the same likelihoods (the models are symmetric), and from three noisy measurements of a
    slow target the initial direction may point backwards, so a filter can settle on a
    negative speed. Before each reset a track whose combined speed is negative has its mileage
    coordinate turned (those components, their covariance rows and columns and the window's
    arc lengths change sign): an exact reparameterisation, so the mileage increases along the
    direction of travel and ``r`` is the direction of travel.

    **The first three steps.** The paper's filter has no estimate before ``k = 4``. Here steps
    ``k = 1, 2, 3`` of the result are the initialisation ``x̂^a_{3|3}`` (combined with the
    initial mode probabilities) read at the chord arc lengths of the first measurements,
    ``s_1 = 0``, ``s_2 = ‖z_2 − z_1‖``, ``s_3 = ŝ_3``: positions on the line from ``z_1`` towards
    ``z_3`` (exactly ``z_1`` at ``k = 1``), the velocity :math:`\dot s_3 (r_x, r_y)` of the
    initialisation, which uses ``z_1..z_3`` (so it is not causal at ``k = 1, 2``); covariance
    ``P^a_{3|3}``, mode probabilities ``initial_probs``. These are also the arc lengths of
    ``z_1..z_3`` in the first reset windows.

    **Mode transitions.** The paper's matrices were lost in extraction; the default
    :data:`DEFAULT_TRANSITION` is a common choice (5% switching per step), with initial
    probabilities ``[0.5, 0.5]`` as the paper gives them.

    Called as every torchsvs estimator, ``tracker(z)`` (``z [B, T, 2]`` or ``[T, 2]``, NaN:
    missing; the first three samples of every track must be present) initialises itself from
    ``z[:, :3]`` and returns a :class:`SeparateModelingResult` of all ``T`` steps;
    ``tracker(z, x0, P0)`` starts instead from an augmented prior ``x0 [B, 8]``, ``P0`` one step
    before ``z[:, 0]`` (no initialisation steps; the reset window starts empty). The step
    protocol is the IMM's (``init`` or :meth:`initialise`, then ``step``/``scan``, whose
    :class:`~torchsvs.filters.imm.IMMResult` :meth:`cartesian` reads).

    Args:
        dt: sampling interval ``T`` (s); a per-step ``dt`` given to a call overrides it.
        q: standard deviation of the mileage models' process noise (m/s², Eqs. (2)-(5)), one
            for both modes or ``(q_ncv, q_nca)``.
        r: measurement noise: a variance, per-axis variances ``[2]`` or ``[2, 2]`` (m²).
        eta_std: standard deviation of the artificial process noise of ``η`` (Eq. (16)).
        window: the sliding window's length ``k_m`` ≥ 3 (the reset fits ``k_m − 1`` samples).
        transition: the ``[2, 2]`` mode transition matrix (NCV, NCA).
        initial_probs: the mode probabilities before ``k = 4``, ``[2]``.
        unscented: filter each mode with a UKF instead of an EKF.
        reset: reset ``η`` by least squares (``False``: the augmented IMM alone, an ablation).
        reset_covariance: ``η``'s covariance at a reset: ``"residual"`` (default),
            ``"measurement"`` or ``"keep"`` (:data:`RESET_COVARIANCES`, see above).
        direction: the reset's direction: ``"rescale"`` (default), ``"normalize"`` or
            ``"raw"`` (:data:`RESET_DIRECTIONS`, see above).
        mixing: how the acceleration the NCV mode lacks is mixed: ``"unbiased"`` (default) or
            ``"zero"`` (:data:`MIXINGS`, see above). With ``"zero"`` both modes' states (and
            their results) are ``[s, ṡ, s̈, η]``; by default the NCV mode's is ``[s, ṡ, η]``.
        floor: variance added to the diagonal of the initialisation's covariance and of ``η``'s
            block at a reset (> 0: both are singular).
        kappa: the initialisation's unscented ``κ``.

    References:
        Zhang Zhuanhua, Zhou Gongjian, J. Syst. Eng. Electron. 33(5), 2022, Secs. 3-4 ·
        Blom, Bar-Shalom, IEEE Trans. Autom. Control 33(8), 1988. doi:10.1109/9.1299 ·
        Yuan, Bar-Shalom, Willett, Mozeson, Pollak, Hardiman, "A multiple IMM estimation
        approach with unbiased mixing for thrusting projectiles", IEEE Trans. Aerosp. Electron.
        Syst. 48(4), 2012 · Granström, Willett, Bar-Shalom, "Systematic approach to IMM mixing
        for unequal dimension states", IEEE Trans. Aerosp. Electron. Syst. 51(4), 2015.
    """

    def __init__(
        self,
        dt: float,
        q: float | Sequence[float] = 0.008,
        r: ArrayLike = 1.0,
        eta_std: ArrayLike = 1e-5,
        window: int = 16,
        transition: Any = DEFAULT_TRANSITION,
        initial_probs: Any = (0.5, 0.5),
        *,
        unscented: bool = False,
        reset: bool = True,
        reset_covariance: str = "residual",
        direction: str = "rescale",
        mixing: str = "unbiased",
        floor: float = 1e-6,
        kappa: float = 0.0,
    ) -> None:
        if isinstance(window, bool) or not isinstance(window, int) or window < 3:
            raise ValueError(
                f"window: expected an integer ≥ 3 (the reset fits the latest window − 1 "
                f"samples), got {window!r}"
            )
        if isinstance(q, (int, float)):
            q_ncv = q_nca = float(q)
        elif isinstance(q, Sequence) and len(q) == 2:
            q_ncv, q_nca = (float(v) for v in q)
        else:
            raise ValueError(f"q: expected a number or a pair (q_ncv, q_nca), got {q!r}")
        if reset_covariance not in RESET_COVARIANCES:
            raise ValueError(
                f"reset_covariance: expected one of {', '.join(map(repr, RESET_COVARIANCES))}, "
                f"got {reset_covariance!r}"
            )
        if direction not in RESET_DIRECTIONS:
            raise ValueError(
                f"direction: expected one of {', '.join(map(repr, RESET_DIRECTIONS))}, "
                f"got {direction!r}"
            )
        if mixing not in MIXINGS:
            raise ValueError(
                f"mixing: expected one of {', '.join(map(repr, MIXINGS))}, got {mixing!r}"
            )
        if not (isinstance(floor, (int, float)) and math.isfinite(floor) and floor > 0):
            raise ValueError(f"floor: expected a number > 0, got {floor!r}")
        zero = mixing == "zero"
        ncv = SeparateModel(MileageConstantVelocity(dt, q_ncv), eta_std, r, embed_acceleration=zero)
        nca = SeparateModel(MileageConstantAcceleration(dt, q_nca), eta_std, r)
        mode_filter = UnscentedKalmanFilter if unscented else ExtendedKalmanFilter
        super().__init__(
            [mode_filter(ncv), mode_filter(nca)],
            transition,
            initial_probs=initial_probs,
            embedding=None if zero else MODE_EMBEDDING,
        )
        self.window = window
        self.reset = bool(reset)
        self.reset_covariance = reset_covariance
        self.direction = direction
        self.mixing = mixing
        self.floor = float(floor)
        self.kappa = float(kappa)

    @property
    def mode_models(self) -> list[SeparateModel]:
        """The augmented models of the NCV and NCA modes."""
        return [f.model for f in self.mode_filters]  # type: ignore[misc]

    # --- initialisation ---

    def initialise(
        self, z: Tensor, dt: float | Tensor | None = None, mode_probs: Any = None
    ) -> IMMState:
        """The state after the first three measurements (the step protocol's start for
        ``z[:, 3:]``): each mode's unscented initialisation, the reset window holding
        ``z_1..z_3`` at their chord arc lengths (class docstring).

        Args:
            z: ``[B, T ≥ 3, 2]`` (the first three are used) or one track ``[T, 2]``.
            dt: a number, per track ``[B]`` or per step ``[B, T]``; default the models'.
            mode_probs: ``[2]`` or ``[B, 2]``; default ``initial_probs``.
        """
        state, _ = self._initialise(z, dt, mode_probs)
        return state

    def _initialise(
        self, z: Tensor, dt: Any, mode_probs: Any
    ) -> tuple[IMMState, tuple[Tensor, Tensor, Tensor, Tensor]]:
        """The state after ``z_1..z_3`` and the estimates of those steps: ``(cartesian
        [B, 3, 4], mean [B, 3, n], cov [B, 3, n, n], mode probabilities [B, 3, M])``."""
        if isinstance(dt, Tensor) and dt.ndim == 0:
            dt = float(dt)
        # In float64 whatever z's dtype: the transform's covariance is singular, and a float32
        # copy of it stays positive definite only with a jitter relative to its scale.
        priors = [
            unscented_initialisation(mdl, z.double(), dt, kappa=self.kappa, floor=self.floor)
            for mdl in self.mode_models
        ]
        single = priors[0].mean.ndim == 1
        zb = z.unsqueeze(0) if single else z
        B, dtype = zb.shape[0], zb.dtype
        means = [p.mean.reshape(B, -1).to(dtype) for p in priors]
        covs = [_jittered(p.cov.reshape(B, *p.cov.shape[-2:]).to(dtype)) for p in priors]
        n = self.model.state_dim
        start = self._start(zb.new_zeros(B, n), torch.eye(n, dtype=dtype), mode_probs, single)
        modes = tuple(FilterState(x, P) for x, P in zip(means, covs, strict=True))
        # The chord arc lengths of z_1, z_2 and the initialisation's ŝ_3 (equal in both modes).
        first = zb[:, :INITIAL_SAMPLES]
        s_3 = means[0][:, 0]
        arc = torch.stack(
            [torch.zeros_like(s_3), (first[:, 1] - first[:, 0]).norm(dim=-1), s_3], dim=1
        )
        aux = self._window_with(first, arc)
        state = start._replace(modes=modes, aux=aux, single=False)
        # The estimates of k = 1..3: the initialisation read at those arc lengths.
        probs = state.log_probs.exp()
        at = [torch.cat([arc.unsqueeze(-1), x[:, None, 1:].expand(-1, 3, -1)], -1) for x in means]
        cartesian = _total(
            [
                probs[:, None, j, None] * mdl.cartesian(x)
                for j, (mdl, x) in enumerate(zip(self.mode_models, at, strict=True))
            ]
        )
        mean, cov = self.combine(
            at,
            [P.unsqueeze(1).expand(-1, 3, -1, -1) for P in covs],
            state.log_probs.unsqueeze(1).expand(-1, 3, -1),
        )
        return state._replace(single=single), (
            cartesian,
            mean,
            cov,
            probs.unsqueeze(1).expand(-1, 3, -1),
        )

    def _window_with(self, z: Tensor, arc_length: Tensor) -> ResetWindow:
        """A reset window ending with the samples ``z [B, k, 2]`` at ``arc_length [B, k]``."""
        width = self.window - 1
        B, k = arc_length.shape
        keep = min(k, width)
        zw = z.new_full((B, width, 2), float("nan"))
        sw = arc_length.new_full((B, width), float("nan"))
        zw = torch.cat([zw[:, : width - keep], z[:, k - keep :]], dim=1)
        sw = torch.cat([sw[:, : width - keep], arc_length[:, k - keep :]], dim=1)
        return ResetWindow(zw, sw)

    # --- the hooks of the IMM: the reset and its window ---

    def adjust_modes(self, state: IMMState) -> IMMState:
        """The least-squares reset of ``η`` before the interaction stage (class docstring),
        at every cycle except the first. It first records the arc length estimated at the
        last step beside that step's measurement and turns the mileage coordinate of a track
        whose estimated speed is negative."""
        aux = state.aux
        if aux is None or state.steps == 0:
            return state
        probs = state.log_probs.exp()
        s_hat = _total([probs[:, j] * m.mean[:, 0] for j, m in enumerate(state.modes)])
        speed = _total([probs[:, j] * m.mean[:, 1] for j, m in enumerate(state.modes)])
        arc = torch.cat([aux.arc_length[:, :-1], s_hat.unsqueeze(-1).to(aux.arc_length.dtype)], 1)
        # Orientation: (s, ṡ, s̈, r, s_l) and -(s, ṡ, s̈, r, s_l) give the same h and the same
        # models' likelihoods; keep the mileage increasing along the direction of travel.
        backwards = (speed < 0).unsqueeze(-1)
        arc = torch.where(backwards, -arc, arc)
        modes = [
            mode._replace(
                mean=torch.where(backwards, mode.mean * sign, mode.mean),
                cov=torch.where(
                    backwards.unsqueeze(-1), mode.cov * (sign.unsqueeze(-1) * sign), mode.cov
                ),
            )
            for mode, sign in zip(state.modes, self._turned(state.modes[0].mean), strict=True)
        ]
        state = state._replace(modes=tuple(modes), aux=aux._replace(arc_length=arc))
        if not self.reset:
            return state
        fit = fit_window_line(aux.z, arc)
        solved = fit.solvable.unsqueeze(-1)
        normalize = self.direction != "raw"
        eta = _eta(fit, normalize)
        if self.reset_covariance != "keep":
            R = self.mode_models[0].meas_cov()
            residual = self.reset_covariance == "residual"
            eta_cov = _reset_covariance(fit, aux.z, R, normalize, residual)
        if self.direction == "rescale":
            tiny = torch.finfo(arc.dtype).tiny
            rho = torch.where(fit.solvable, fit.slope.norm(dim=-1).clamp_min(tiny), 1.0)
            anchor = torch.where(fit.solvable, fit.s_l, 0.0).unsqueeze(-1)
            arc = anchor + rho.unsqueeze(-1) * (arc - anchor)
            state = state._replace(aux=aux._replace(arc_length=arc))
        adjusted = []
        for mdl, mode in zip(self.mode_models, state.modes, strict=True):
            b = mdl.base_dim
            x, P = mode.mean, mode.cov
            base, P_base = x[:, :b], P[:, :b, :b]
            if self.direction == "rescale":
                offset = torch.zeros_like(base)
                offset[:, 0] = anchor.squeeze(-1)
                base = offset + rho.unsqueeze(-1) * (base - offset)
                P_base = P_base * (rho * rho)[:, None, None]
            eta_j = torch.where(solved, eta.to(x.dtype), x[:, b:])
            x = torch.cat([base, eta_j], dim=-1)
            if self.reset_covariance == "keep":
                scale = torch.ones_like(x)
                if self.direction == "rescale":
                    scale = torch.cat([rho.unsqueeze(-1).expand(-1, b), scale[:, b:]], -1)
                P = P * scale.unsqueeze(-1) * scale.unsqueeze(-2)
            else:
                B = x.shape[0]
                eye = torch.eye(eta_cov.shape[-1], dtype=P.dtype)
                reset = torch.cat(
                    [
                        torch.cat([P_base.expand(B, b, b), P.new_zeros(B, b, 5)], -1),
                        torch.cat([P.new_zeros(B, 5, b), eta_cov + self.floor * eye], -1),
                    ],
                    dim=-2,
                )
                P = torch.where(solved.unsqueeze(-1), reset, P)
            adjusted.append(mode._replace(mean=x, cov=P))
        return state._replace(modes=tuple(adjusted))

    def _turned(self, like: Tensor) -> list[Tensor]:
        """Per mode, the signs ``[n]`` that turn the mileage coordinate: ``−1`` for ``s, ṡ, s̈,
        r_x, r_y, s_l``, ``+1`` for ``x_l, y_l``."""
        signs = []
        for mdl in self.mode_models:
            sign = torch.full((mdl.state_dim,), -1.0, dtype=like.dtype)
            sign[mdl.eta_index[0]] = sign[mdl.eta_index[2]] = 1.0
            signs.append(sign)
        return signs

    def update_aux(self, state: IMMState, z: Tensor, dt: Tensor | None, u: Tensor | None) -> Any:
        """Appends the step's measurement to the reset window (its arc length follows at the
        next cycle)."""
        aux = state.aux
        if aux is None:
            B = z.shape[0]
            aux = self._window_with(z.new_zeros(B, 0, 2), z.new_zeros(B, 0))
        B = max(aux.z.shape[0], z.shape[0])
        zw = torch.cat([aux.z[:, 1:].expand(B, -1, -1), z.expand(B, -1).unsqueeze(1)], dim=1)
        nan = aux.arc_length.new_full((B, 1), float("nan"))
        sw = torch.cat([aux.arc_length[:, 1:].expand(B, -1), nan], dim=1)
        return ResetWindow(zw, sw)

    # --- reading a result ---

    def cartesian(self, result: IMMResult) -> Tensor:
        """The Cartesian estimate ``[..., 4]`` (``[x, vx, y, vy]``) of an IMM result of this
        tracker: each mode's :meth:`~torchsvs.models.SeparateModel.cartesian`, combined with the
        mode probabilities."""
        probs = result.mode_probs
        parts = [
            mdl.cartesian(r.mean) for mdl, r in zip(self.mode_models, result.modes, strict=True)
        ]
        return _total([probs[..., j, None] * part for j, part in enumerate(parts)])

    # The IMM's call, with the prior optional and a richer result.
    @outside_dynamo
    def forward(  # type: ignore[override]
        self,
        z: Tensor,
        x0: Tensor | None = None,
        P0: Tensor | None = None,
        *,
        mode_probs: Any = None,
        u: Tensor | None = None,
        dt: float | Tensor | None = None,
        psi: Tensor | None = None,
        generator: torch.Generator | None = None,
        keep: str = "all",
    ) -> SeparateModelingResult:
        """Tracks every road target: ``z [B, T, 2]`` (or ``[T, 2]``; NaN: missing), from the
        unscented initialisation of ``z[:, :3]`` (``x0 = P0 = None``, then ``T ≥ 4``) or from an
        augmented prior ``x0``, ``P0`` one step before ``z[:, 0]``; ``mode_probs``, ``dt``,
        ``keep`` as for :class:`~torchsvs.IMM`. Returns a :class:`SeparateModelingResult`."""
        self.check_psi(psi)
        check_keep(keep)
        if (x0 is None) != (P0 is None):
            raise ValueError(
                "x0, P0: give both (an augmented prior) or neither (the unscented "
                f"initialisation from z[:, :3]); got x0 {'None' if x0 is None else 'given'}, "
                f"P0 {'None' if P0 is None else 'given'}"
            )
        initialising = x0 is None
        if initialising:
            if isinstance(z, Tensor) and z.ndim in (2, 3) and z.shape[-2] <= INITIAL_SAMPLES:
                raise ValueError(
                    f"z: expected T ≥ {INITIAL_SAMPLES + 1} steps (three initialise the "
                    f"tracker), got shape {tuple(z.shape)}"
                )
            n = self.model.state_dim
            like = z.dtype if isinstance(z, Tensor) and z.is_floating_point() else torch.float64
            x0, P0 = torch.zeros(n, dtype=like), torch.eye(n, dtype=like)  # (checks only)
        inputs = prepare_inputs(self.model, z, x0, P0, u=u, dt=dt, generator=generator, keep=keep)
        with threads_for(inputs.batch, self.model.state_dim):
            if initialising:
                dt_first = inputs.dt
                state, first = self._initialise(inputs.z, dt_first, mode_probs)
                state = state._replace(single=False)
                rest = inputs.window(INITIAL_SAMPLES, inputs.steps)
            else:
                start = self._start(inputs.x0, inputs.P0, mode_probs, inputs.single)
                state, first, rest = start._replace(single=False), None, inputs
            _, imm = self._scan(state, rest)
        cartesian = self.cartesian(imm)
        mean, cov, probs = imm.mean, imm.cov, imm.mode_probs
        if first is not None:
            cartesian = torch.cat([first[0], cartesian], dim=1)
            mean = torch.cat([first[1], mean], dim=1)
            cov = torch.cat([first[2], cov], dim=1)
            probs = torch.cat([first[3], probs], dim=1)
        imm = self.trim(imm, keep)
        result = SeparateModelingResult(
            cartesian=cartesian,
            mean=mean,
            cov=None if keep == "mean" else cov,
            mode_probs=probs,
            imm=imm,
            log_likelihood=imm.log_likelihood,
        )
        return drop_batch(result) if inputs.single else result


def _jittered(P: Tensor) -> Tensor:
    """``P [B, n, n]`` plus ``64 ε`` of its largest variance on the diagonal (``ε`` of its
    dtype): a float32 copy of a covariance with tiny eigenvalues stays positive definite."""
    scale = P.diagonal(dim1=-2, dim2=-1).amax(-1).clamp_min(1.0)
    eye = torch.eye(P.shape[-1], dtype=P.dtype)
    return P + (64 * torch.finfo(P.dtype).eps * scale)[:, None, None] * eye


def _total(terms: list[Tensor]) -> Tensor:
    """The sum of ``terms``, added in order."""
    total = terms[0]
    for term in terms[1:]:
        total = total + term
    return total
