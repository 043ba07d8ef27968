r"""The separate-modeling tracker's unscented initialisation (Zhang & Zhou 2022, Sec. 4,
Eqs. (17)-(21)): the augmented state and its covariance from the first three measurements.

The paper's equations were lost in extraction; what follows rebuilds them from its text and the
cited literature (equation numbers the paper's where its text names them, inferred otherwise).

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

from torchsvs.filters.separate.batch import batched
from torchsvs.models.mileage import SeparateModel

#: Measurements the initialisation uses (the filter starts at the fourth).
INITIAL_SAMPLES = 3


class AugmentedPrior(NamedTuple):
    """The unscented initialisation of the augmented state, ``x̂^a_{3|3}`` and ``P^a_{3|3}``."""

    mean: Tensor  #: [B, n]
    cov: Tensor  #: [B, n, n]


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
    z, single = batched(z, "z", 3)
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
    z, single = batched(z, "z", 3)
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
