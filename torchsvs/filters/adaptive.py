r"""Adaptive measurement noise: ``R_k`` from the spread of the differenced recent measurements.

Eqs. (29)-(30) of Bermúdez Ordoñez et al. 2020 (after Foussier et al. 2014, their ref. 14): at
each step ``k`` and for each measured component ``i``,

.. math::
    \sigma^i_{\mathrm{noise},k} = \frac{\operatorname{std}(\operatorname{diff}(S^i_k))}{\sqrt 2},
    \qquad R_k = \operatorname{diag}\big((\sigma^1_{\mathrm{noise},k})^2, \dots,
    (\sigma^m_{\mathrm{noise},k})^2\big),

where ``S^i_k`` is the recent segment of component ``i``: its last ``window`` measurements up to
and including ``z_k`` (the paper says "small-signal segment" and gives no length). ``diff`` takes
the differences of adjacent samples and ``std`` is MATLAB's (the paper's code): the sample standard
deviation about the mean, normalised by ``count − 1``. The divisor is printed as ``2`` in the text
we have, its radical lost in extraction: ``√2`` is the one that makes ``σ²`` the noise variance,
since ``Var(v_k − v_{k−1}) = 2σ²`` for white noise ``v``.

Why differencing removes the signal: ``z_k = s_k + v_k`` gives ``Δz_k = Δs_k + Δv_k``; a signal
that varies slowly against the sampling changes little from one sample to the next, and the
mean that ``std`` subtracts removes a constant rate of change over the window (a linear trend
of ``s``). What remains is the noise and the *change* of ``Δs`` over the window: the estimate is

.. math::
    E[\hat\sigma^2] \approx \sigma^2 \tfrac{N}{N-1}
        + \tfrac12 \operatorname{var}_{\mathrm{window}}(\Delta s)

for ``N`` samples (the first term is exact for white noise: adjacent differences are correlated,
``−σ²``, and the mean of ``N − 1`` differences telescopes). For a non-linear measurement such as
a slant range ``‖p − p_station‖`` this is the range's curvature: with speed ``v``, the range's
second difference is about ``v_⊥² T² / r`` per step, so over ``N`` samples ``½ var(Δs) ≈
(v_⊥² T²/r)² (N−1)² / 24``, small far from the stations and growing as the aircraft passes one.
The estimate uses ``z`` directly: no state estimate enters it, so it is the same for the KF, EKF
and SVSF.

Conventions of this implementation (the paper leaves them open):

* Causal: ``R_k`` uses measurements up to ``k`` only (``include_current=False``: up to
  ``k − 1``, the order of Algorithm 1, which forms ``R`` after the update of the step before).
* Missing values (NaN) are skipped: only differences of two adjacent observed samples count.
* Until a component's window holds ``min_differences`` differences, its variance is the model's
  ``R``; a component whose variance is estimated has no covariance with the others (Eq. (29) is
  diagonal), the components not yet estimated keep their block of the model's ``R``.
* ``floor`` bounds ``σ`` from below, so a constant segment cannot make ``R`` singular.

References:
    Bermúdez Ordoñez, Arnaldo Valdés, Gómez Comendador, "Engineering Applications of Adaptive
    Kalman Filtering Based on Singular Value Decomposition (SVD)", Appl. Sci. 10(15):5168, 2020,
    Eqs. (29)-(30). doi:10.3390/app10155168 ·
    Foussier, Teichmann, Jia, Misgeld, Leonhardt, "An adaptive Kalman filter approach for
    cardiorespiratory signal extraction and fusion of non-contacting sensors", BMC Med. Inform.
    Decis. Mak. 14:37, 2014. doi:10.1186/1472-6947-14-37
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor


@dataclass(frozen=True)
class AdaptiveNoise:
    """The adaptive ``R_k`` of Eqs. (29)-(30) (see the module's doc), a filter option
    (``KalmanFilter(model, adaptive_noise=AdaptiveNoise(window=20))``, the EKF and SVSF alike).

    Args:
        window: samples ``N ≥ 3`` per segment ``S^i_k`` (``N − 1`` differences).
        floor: the smallest ``σ_noise`` (``z``'s units), ``≥ 0``.
        min_differences: observed differences a component's window needs before its variance is
            estimated (the model's ``R`` until then); ``2 ≤ · ≤ window − 1``, default
            ``window − 1`` (a full window).
        include_current: whether ``S^i_k`` ends at ``z_k`` (default, Eq. (29)'s index) or at
            ``z_{k−1}`` (Algorithm 1's order).
    """

    window: int
    floor: float = 0.0
    min_differences: int | None = None
    include_current: bool = True

    def __post_init__(self) -> None:
        window = self.window
        if isinstance(window, bool) or not isinstance(window, int) or window < 3:
            raise ValueError(
                f"window: expected an integer >= 3 (samples per segment; the std of its "
                f"differences needs two of them), got {window!r}"
            )
        floor = self.floor
        if isinstance(floor, bool) or not isinstance(floor, (int, float)):
            raise TypeError(f"floor: expected a number >= 0, got {type(floor).__name__}")
        if not (math.isfinite(floor) and floor >= 0):
            raise ValueError(f"floor: expected a finite number >= 0, got {floor!r}")
        least = self.min_differences
        if least is not None and (
            isinstance(least, bool) or not isinstance(least, int) or not 2 <= least <= window - 1
        ):
            raise ValueError(
                f"min_differences: expected an integer in [2, window - 1] = [2, {window - 1}] "
                f"or None, got {least!r}"
            )
        if not isinstance(self.include_current, bool):
            raise TypeError(
                f"include_current: expected a bool, got {type(self.include_current).__name__}"
            )

    @property
    def lag(self) -> int:
        """Steps between ``z_k`` and the last sample of ``S_k`` (0 or 1)."""
        return 0 if self.include_current else 1

    @property
    def rows_needed(self) -> int:
        """Rows before a step that its segment may reach back to (what a chunk carries)."""
        return self.window - 1 + self.lag

    def covariance(self, R: Tensor, z: Tensor, earlier: Tensor | None = None) -> Tensor:
        """``R_k`` of every step of ``z [B, T, m]`` (NaN: missing), ``[B, T, m, m]``, Eq. (29).

        ``earlier [B, k, m]``: the raw rows before ``z[:, 0]`` (any ``k``; the last
        :attr:`rows_needed` of them matter), ``None`` at the start of a run; ``R [m, m]``: the
        model's noise, which components without a full enough window keep."""
        rows = z if earlier is None else torch.cat([earlier.to(z.dtype), z], dim=1)
        variance, count = differenced_variance(rows, self.window, self.lag, last=z.shape[1])
        least = self.window - 1 if self.min_differences is None else self.min_differences
        estimated = count >= least  # [B, T, m]
        variance = variance.clamp_min(self.floor**2)
        touched = estimated.unsqueeze(-1) | estimated.unsqueeze(-2)
        return torch.where(touched, torch.diag_embed(variance), R.to(z.dtype))

    def carried(self, earlier: Tensor | None, z: Tensor) -> Tensor:
        """The raw rows the next chunk's segments may reach back to: the last
        :attr:`rows_needed` of ``earlier`` followed by ``z [B, T, m]``."""
        rows = z if earlier is None else torch.cat([earlier.to(z.dtype), z], dim=1)
        return rows[:, -self.rows_needed :]


def differenced_variance(
    rows: Tensor, window: int, lag: int = 0, last: int | None = None
) -> tuple[Tensor, Tensor]:
    """``σ²_noise`` of Eq. (30) at each of the ``last`` rows (default all) of ``rows [B, K, m]``
    and the observed differences behind it, ``[B, last, m]`` each: half the sample variance
    (``count − 1`` normalised) of the adjacent differences among the ``window`` rows ending
    ``lag`` rows before it (NaN rows skipped; rows before the first count as missing). Where
    fewer than two differences were observed the variance is 0 (the caller falls back on the
    model's ``R``).

    Two passes (mean, then squared deviations) over the ``window − 1`` differences of every
    segment, each a slice of the run: memory of a few ``[B, last, m]``, not one per sample of a
    segment. Computed on NaN-filled values and masked afterwards, so values and gradients stay
    finite."""
    B, K, m = rows.shape
    out = K if last is None else last
    pad = rows.new_full((B, window - 1 + lag, m), math.nan)
    padded = torch.cat([pad, rows], dim=1)
    seen = ~torch.isnan(padded)
    filled = padded.nan_to_num(0.0)
    diff = filled[:, 1:] - filled[:, :-1]  # difference j: between padded rows j and j + 1
    valid = seen[:, 1:] & seen[:, :-1]
    # Row r of ``rows`` is padded row r + window - 1 + lag; its segment (rows r - window + 1 -
    # lag .. r - lag) holds differences r .. r + window - 2: the j-th of the last ``out`` rows'
    # segments is one slice.
    parts = [slice(K - out + j, K + j) for j in range(window - 1)]
    count = sum(
        (valid[:, j] for j in parts), torch.zeros_like(valid[:, parts[0]], dtype=torch.long)
    )
    scale = count.clamp_min(1).to(rows.dtype)
    zero = rows.new_zeros(())
    mean = sum((torch.where(valid[:, j], diff[:, j], zero) for j in parts), zero) / scale
    spread = sum((torch.where(valid[:, j], diff[:, j] - mean, zero).square() for j in parts), zero)
    variance = spread / (count - 1).clamp_min(1).to(rows.dtype)
    return 0.5 * variance, count  # Var(v_k − v_{k−1}) = 2σ²: Eq. (30)'s √2, squared


def check_adaptive_noise(value: Any) -> AdaptiveNoise | None:
    """A filter's ``adaptive_noise`` argument, checked."""
    if value is not None and not isinstance(value, AdaptiveNoise):
        raise TypeError(
            "adaptive_noise: expected an AdaptiveNoise (torchsvs.filters.AdaptiveNoise(window=N)) "
            f"or None, got {type(value).__name__}"
        )
    return value
