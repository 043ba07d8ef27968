"""Recorded tracks: track files and ADS-B samples into padded batches, estimates back out.

Knows no estimator. ``read_tracks`` gives a :class:`RecordedTracks` batch (``z [B, T, m]`` with
NaN where missing or padded, per-step ``dt [B, T]``, lengths, priors ``x0, P0`` from the first
measurements, ids and times) and a :class:`RowReport` saying what happened to every row;
``write_estimates`` writes one output row per input row.
"""

from typing import TYPE_CHECKING

from torchsvs.lazy_names import lazy_names

if TYPE_CHECKING:
    from torchsvs.datasets.describe import InputDescription, describe_input
    from torchsvs.datasets.noise_estimate import NoiseEstimate, estimate_noise
    from torchsvs.datasets.paths import check_output
    from torchsvs.datasets.priors import Prior, two_point_prior
    from torchsvs.datasets.reading import TrackBlock, track_blocks
    from torchsvs.datasets.rows import (
        NOTES,
        SET_ASIDE,
        Columns,
        InputWarning,
        RowReport,
    )
    from torchsvs.datasets.steps import TrackSteps, group_rows
    from torchsvs.datasets.times import TIME_UNITS
    from torchsvs.datasets.track_noise import noise_spread
    from torchsvs.datasets.tracks import (
        RecordedTracks,
        meas_variance,
        padded_batch,
        read_tracks,
        with_prior,
    )
    from torchsvs.datasets.writing import (
        EstimateWriter,
        estimate_table,
        state_names,
        write_estimates,
    )

#: Where each name lives: imported when first used, so reading a file (``rows``, ``steps``,
#: ``reading``, ``describe``: numpy and Arrow) does not import torch
#: (:class:`~torchsvs.datasets.reading.ReadAhead`).
_HOMES = {
    "InputDescription": "describe",
    "describe_input": "describe",
    "NoiseEstimate": "noise_estimate",
    "estimate_noise": "noise_estimate",
    "noise_spread": "track_noise",
    "check_output": "paths",
    "Prior": "priors",
    "two_point_prior": "priors",
    "TrackBlock": "reading",
    "track_blocks": "reading",
    "NOTES": "rows",
    "SET_ASIDE": "rows",
    "TIME_UNITS": "times",
    "Columns": "rows",
    "InputWarning": "rows",
    "RowReport": "rows",
    "TrackSteps": "steps",
    "group_rows": "steps",
    "RecordedTracks": "tracks",
    "meas_variance": "tracks",
    "read_tracks": "tracks",
    "with_prior": "tracks",
    "padded_batch": "tracks",
    "EstimateWriter": "writing",
    "estimate_table": "writing",
    "state_names": "writing",
    "write_estimates": "writing",
}


__getattr__, __dir__ = lazy_names(__name__, _HOMES, globals())


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
    "padded_batch",
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
