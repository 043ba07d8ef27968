r"""Two estimators' estimates blended, weighted by their truth-free error (SURE).

Where two estimators of a file err differently (the Kalman smoother's one motion model against
the IMM smoother's two), their blend :math:`h = (1 - w)\,g + w f` can be better than either:
its error is :math:`(1 - w)\,e_g + w\,e_f`, and the errors' cross term is below their mean
square wherever they are not the same. With ``auto`` choosing such blends, the recorded-tracks
benchmark's 44 sets and modes came to 0.954x the Kalman smoother on average (0.968x choosing
one estimator per file), 0.93-0.98x on airliners at their own report times where the Kalman
and IMM smoothers are about equal (``experiments/results/recorded_tracks.md``).

Its Stein unbiased risk estimate (:mod:`torchsvs.accuracy`) follows from the two's and one
more sum per chunk, :math:`C = \sum (f - g)^2` over the observed components: for any ``w``

.. math::
    \|z - h\|^2 = (1 - w)\,\|z - g\|^2 + w\,\|z - f\|^2 - w (1 - w)\,C,
    \qquad \nabla\!\cdot h = (1 - w)\,\nabla\!\cdot g + w\,\nabla\!\cdot f,

(the first an identity of squares, the second the divergence's linearity), so the blend's
estimated MSE is a quadratic in ``w`` whose least is at

.. math::
    w^* = \frac{\sum_i \big(\|z-g\|^2_i - \|z-f\|^2_i + C_i
          - 2\sigma_i^2 (\nabla\!\cdot f - \nabla\!\cdot g)_i\big) / n_i}
          {2 \sum_i C_i / n_i},

axis ``i`` with ``n_i`` observed components, clipped to ``[0, 1]``. This module holds those
formulas on :class:`~torchsvs.accuracy.RiskTerms`; :func:`torchsvs.estimating.estimate_group`
runs a :class:`~torchsvs.recipes.Blend` with them and ``--estimator auto`` chooses one
(:func:`torchsvs.selection.blend_candidate`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from torch import Tensor

from torchsvs.accuracy import RiskTerms, chunk_terms


def cross_terms(observed: Tensor, first: Tensor, second: Tensor, group: np.ndarray) -> RiskTerms:
    """``C``, the two estimates' squared difference summed over each chunk's observed components
    (in the ``residual`` field; no divergence), for positions ``first``, ``second``
    ``[B, T, m]`` of measurements observed where ``observed``; the chunks' ``track`` is
    ``group`` ``[B]``'s entry, in track order (:meth:`~torchsvs.accuracy.RiskTerms.
    in_track_order`)."""
    difference = (second.double() - first.double()).nan_to_num(0.0)
    square = difference.square().where(observed, 0.0)
    terms = chunk_terms(observed, square, square.new_zeros(()).expand_as(square))
    terms.track = group[terms.track]
    return terms.in_track_order()


def _aligned(first: RiskTerms, second: RiskTerms, cross: RiskTerms) -> None:
    """Checks that the three hold the same chunks in the same order."""
    for name, terms in (("second", second), ("cross", cross)):
        same = np.array_equal(terms.count, first.count) and np.array_equal(terms.track, first.track)
        if not same:
            raise ValueError(f"{name}: expected the terms of the same chunks, in track order")


def best_weight(
    first: RiskTerms, second: RiskTerms, cross: RiskTerms, meas_var: Sequence[float]
) -> float:
    """:math:`w^*`, the weight of ``second`` whose blend has the least estimated MSE (the
    module's formula; all three in track order), in ``[0, 1]``; 0 where they do not differ."""
    _aligned(first, second, cross)
    counts = first.count.sum(axis=0)
    if not (counts > 0).all():
        return 0.0
    spread = cross.residual.sum(axis=0)
    gained = first.errors(meas_var).sum(axis=0) - second.errors(meas_var).sum(axis=0)
    slope = float(((gained + spread) / counts).sum())
    curvature = float((2.0 * spread / counts).sum())
    if not curvature > 0:
        return 0.0
    return float(np.clip(slope / curvature, 0.0, 1.0))


def blended_terms(
    first: RiskTerms, second: RiskTerms, cross: RiskTerms, weight: float
) -> RiskTerms:
    """The SURE sums of the blend ``(1 − w) first + w second`` per chunk (the module's
    identities; all three in track order)."""
    _aligned(first, second, cross)
    w = weight
    residual = (1 - w) * first.residual + w * second.residual - w * (1 - w) * cross.residual
    divergence = (1 - w) * first.divergence + w * second.divergence
    return RiskTerms(residual, divergence, first.count.copy(), first.track.copy())
