r"""The separate-modeling tracker's least-squares reset of the trajectory parameters over a
sliding window (Zhang & Zhou 2022, Sec. 4, Eqs. (36)-(40)) and the covariance of the reset.

The paper's equations were lost in extraction; what follows rebuilds them from its text
(equation numbers the paper's where its text names them, inferred otherwise).

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
unit drift by it (see :class:`~torchsvs.SeparateModelingTracker`, which by default moves it
into the mileage state instead).

**The reset's covariance** (not in the paper's text): per axis the LS problem is
:math:`V\theta = \mathbf x` with noise of covariance :math:`R` between the axes, so
:math:`\mathrm{Cov}([x_l^*, r_x^*, y_l^*, r_y^*]') = \tilde R\otimes(V'V)^{-1}`,
:math:`(V'V)^{-1} = G^{-1}G^{-\prime}`, carried through a normalisation's Jacobian
:math:`(I - uu')/\rho` (:func:`reset_covariance`); :math:`\tilde R` is :math:`R` or the
window's residual covariance pooled with it. :class:`~torchsvs.SeparateModelingTracker` sets
``η``'s block to it at each reset (``docs/guide/separate_modeling.md`` says why).

References:
    Zhang Zhuanhua, Zhou Gongjian, J. Syst. Eng. Electron. 33(5), 2022, Sec. 4.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.filters.separate.batch import batched


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
    positions, single = batched(positions, "positions", 3)
    arc_length, _ = batched(arc_length, "arc_length", 2)
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


def parameters_of_fit(fit: LineFit, normalize: bool) -> Tensor:
    """``η* [B, 5]`` of a fit (Eq. (40)), its direction normalised or not; NaN where
    unsolvable."""
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
    eta = parameters_of_fit(fit_window_line(positions, arc_length, mask), normalize)
    return eta.squeeze(0) if single else eta


#: Weight, in residuals, of the sensor noise ``R`` in the residual estimate of the reset's
#: covariance (:func:`reset_covariance`).
PRIOR_RESIDUALS = 2.0


def covariance_of_fit(
    fit: LineFit, positions: Tensor, R: Tensor, normalize: bool, residual: bool
) -> Tensor:
    """:func:`reset_covariance` of a fit ``[B, 5, 5]`` (finite and meaningless where it is
    unsolvable)."""
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
    cov = covariance_of_fit(fit, positions, R, normalize, residual)
    cov = torch.where(fit.solvable[:, None, None], cov, torch.zeros_like(cov))
    return cov.squeeze(0) if single else cov
