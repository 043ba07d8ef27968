"""Recorded tracks: track files and ADS-B samples into padded batches, estimates back out.

Knows no estimator. ``read_tracks`` gives a :class:`RecordedTracks` batch (``z [B, T, m]`` with
NaN where missing or padded, per-step ``dt [B, T]``, lengths, priors ``x0, P0`` from the first
measurements, ids and times) and a :class:`RowReport` saying what happened to every row;
``write_estimates`` writes one output row per input row.
"""

from torchsvs.datasets.describe import InputDescription, describe_input
from torchsvs.datasets.noise_estimate import NoiseEstimate, estimate_noise, noise_spread
from torchsvs.datasets.paths import check_output
from torchsvs.datasets.priors import Prior, two_point_prior
from torchsvs.datasets.reading import (
    TrackBlock,
    meas_variance,
    read_tracks,
    track_blocks,
    with_prior,
)
from torchsvs.datasets.rows import NOTES, SET_ASIDE, TIME_UNITS, Columns, InputWarning, RowReport
from torchsvs.datasets.tracks import RecordedTracks, TrackSteps, group_rows
from torchsvs.datasets.writing import EstimateWriter, estimate_table, state_names, write_estimates

__all__ = [
    "NOTES",
    "SET_ASIDE",
    "TIME_UNITS",
    "Columns",
    "EstimateWriter",
    "InputDescription",
    "InputWarning",
    "NoiseEstimate",
    "Prior",
    "RecordedTracks",
    "RowReport",
    "TrackBlock",
    "TrackSteps",
    "check_output",
    "describe_input",
    "estimate_noise",
    "noise_spread",
    "estimate_table",
    "group_rows",
    "meas_variance",
    "read_tracks",
    "state_names",
    "track_blocks",
    "two_point_prior",
    "with_prior",
    "write_estimates",
]
