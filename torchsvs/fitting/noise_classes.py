"""Each track at its own measurement noise, given per row (``--noise-col``): sensors of
different quality in one file (ADS-B's position accuracy categories, a fleet's GPS receivers
and their reported accuracy).

One noise level for a file whose tracks' noise spans a factor of 3 either way fits none of
them: with each track's σ drawn from σ/3 to 3σ, the estimators came out at 0.59-1.00 of the
measurements' error and their error estimate at 0.15-0.68 of the truth
(``experiments/results/recorded_mixed.md``). Where the file carries each row's accuracy, each
track runs at its own; where it does not, each track's is read off its own positions
(:mod:`torchsvs.datasets.track_noise`) where the run finds that clearly better
(:func:`~torchsvs.sample_accuracy.with_track_noise`: read track by track, the noise takes a
track's motion for noise where the noise is small, airliners at σ 3 m reading up to 10 m).

A track's noise is the median over its rows of the column's variance (the column holds the
standard deviation per row, in the positions' units), on a grid of factors of the file's
(:data:`FACTOR_STEP`); each class of tracks runs as a file of its noise (its settings
:func:`scaled_settings`, its estimator :func:`noise_scaled`), and its error estimate's terms
are written at the file's noise from each track's own (:func:`at_file_noise`), so the run's
totals read every track at its own.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator, Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor, nn

from torchsvs.accuracy import RiskTerms
from torchsvs.constraints import SPDMatrix, scaled_copy
from torchsvs.datasets import RecordedTracks
from torchsvs.datasets.track_noise import read_track_noise, shrunk_ratios
from torchsvs.recipes import Settings

#: A track's noise variance is the file's times a power of this (σ within 4.5% of its own):
#: the tracks of one power run together.
FACTOR_STEP = 2.0**0.25


def column_noise(values: Tensor, observed: Tensor, column: str) -> float:
    """The file's noise variance: the mean over the observed rows of the column's squared
    standard deviations ``values [B, T]`` (NaN where a row has none), so that the measurements'
    own error the run prints beside its estimate is theirs."""
    given = values[observed & torch.isfinite(values)]
    if given.numel() == 0:
        raise ValueError(
            f"noise column {column!r}: expected a standard deviation on the rows with a "
            "position, got none"
        )
    _check_positive(given, column)
    return float(given.to(torch.float64).square().mean())


def _check_positive(given: Tensor, column: str) -> None:
    if bool((given <= 0).any()):
        raise ValueError(
            f"noise column {column!r}: expected standard deviations > 0, got "
            f"{float(given.min()):.4g}"
        )


def column_ratios(values: Tensor, observed: Tensor, meas_var: Sequence[float]) -> Tensor:
    """``[B]`` float64 each track's noise variance over the file's ``meas_var``: the median of
    its observed rows' squared standard deviations ``values [B, T]`` over their mean; 1 for a
    track without any."""
    squares = values.to(torch.float64).square()
    squares = squares.masked_fill(~(observed & torch.isfinite(squares)), math.nan)
    ratio = squares.nanmedian(dim=1).values / (sum(meas_var) / len(meas_var))
    return torch.where(torch.isfinite(ratio), ratio, torch.ones_like(ratio))


def on_grid(ratios: Tensor) -> Tensor:
    """``[B]`` the tracks' :func:`column_ratios` on the grid of :data:`FACTOR_STEP`: the noise
    each track's class runs at (its error estimate reads its own, :func:`at_file_noise`)."""
    return FACTOR_STEP ** (ratios.log() / math.log(FACTOR_STEP)).round()


class NoiseClass(NamedTuple):
    """A group's tracks at one noise (:func:`classes_of`)."""

    factor: float  #: their noise variance over the file's (on the grid)
    members: Tensor  #: [k] int64 those of the group's tracks
    settings: Settings  #: the file's settings at their noise (:func:`scaled_settings`)
    #: each track's own noise over the file's, by the block's track number (what error terms'
    #: chunks name)
    ratio_of: np.ndarray

    def at_file_noise(self, terms: RiskTerms) -> RiskTerms:
        """Their error terms at the file's noise from each track's own (:func:`at_file_noise`)."""
        return at_file_noise(terms, self.ratio_of[terms.track])


def classes_of(
    tracks: RecordedTracks, group: np.ndarray, settings: Settings
) -> Iterator[NoiseClass]:
    """The noise classes of a group's ``tracks`` (the block's tracks ``group [B]``) where each
    has its own noise (:func:`track_ratios` on :func:`on_grid`)."""
    ratios = track_ratios(tracks, settings)
    factors = on_grid(ratios)
    ratio_of = np.ones(int(group.max()) + 1 if len(group) else 0)
    ratio_of[group] = ratios.numpy()
    for factor in torch.unique(factors).tolist():
        index = torch.nonzero(factors == factor).flatten()
        yield NoiseClass(factor, index, scaled_settings(settings, factor), ratio_of)


def track_ratios(tracks: RecordedTracks, settings: Settings) -> Tensor:
    """``[B]`` float64 each track's noise variance over the file's ``meas_var``: from the
    column (``settings.noise_column``, :func:`column_ratios`) or read off each track's own
    positions and shrunk towards the file's (``settings.track_noise``,
    :func:`~torchsvs.datasets.track_noise.shrunk_ratios`)."""
    assert settings.meas_var is not None and settings.own_noise
    column = settings.noise_column
    if column is None:
        assert settings.track_noise is not None
        mean, tau = settings.track_noise
        read = read_track_noise(tracks.z, tracks.dt, settings.meas_var)
        return shrunk_ratios(read, mean, tau)
    observed = ~torch.isnan(tracks.z).all(-1)
    values = tracks.extra[column]
    _check_positive(values[observed & torch.isfinite(values)], column)  # (a block past the plan's)
    return column_ratios(values, observed, settings.meas_var)


def scaled_settings(settings: Settings, factor: float) -> Settings:
    """The settings with the noise variance times ``factor`` (a blend's second's too): a
    class's own, that its estimates, outlier screen and error estimate run with."""
    assert settings.meas_var is not None
    meas_var = [v * factor for v in settings.meas_var]
    blend = settings.blend
    if blend is not None:
        blend = replace(blend, meas_var=list(meas_var), noise_column=None, track_noise=None)
    std_se = settings.meas_std_se  # (read off the data: the file's level's, at the class's)
    if std_se is not None:
        std_se = [e * math.sqrt(factor) for e in std_se]
    return replace(
        settings,
        meas_var=meas_var,
        meas_std_se=std_se,
        blend=blend,
        noise_column=None,
        track_noise=None,
    )


def noise_scaled(
    estimator: nn.Module, factor: float
) -> contextlib.AbstractContextManager[nn.Module]:
    """A copy of the estimator with every model's measurement noise ``R`` times ``factor``
    (each once: the IMM's modes share their model's; the estimator itself where the factor is
    1: :func:`~torchsvs.constraints.scaled_copy`)."""

    def noises(scaled: nn.Module) -> list[SPDMatrix]:
        return [R for m in scaled.modules() if isinstance(R := getattr(m, "R", None), SPDMatrix)]

    return scaled_copy(estimator, factor, noises)


def at_file_noise(terms: RiskTerms, ratio: np.ndarray) -> RiskTerms:
    """SURE terms written so that SURE at the file's noise is theirs at each track's own,
    ``r (2 d' − n) = g r (2 d − n)`` with ``ratio [C]`` each chunk's track's noise over the
    file's (its own, not its class's: SURE is unbiased at the measurements' true noise whatever
    the linear estimate, and 9% off in the variance moved it by 3 times the error on tracks of
    σ 9 m): the run's totals, its per-track errors and its checks then read them as any other."""
    count = terms.count
    g = np.asarray(ratio, dtype=np.float64).reshape(-1, 1)
    divergence = 0.5 * (g * (2.0 * terms.divergence - count) + count)
    return RiskTerms(terms.residual, divergence, count, terms.track)
