"""One estimator call of ``torchsvs track`` and what it hands back: a group of a block's tracks
(:class:`GroupBatch`) and its estimates at the block's steps (:class:`StepEstimates`), the types
every engine passes between processes (:mod:`torchsvs.estimating` makes them)."""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from torchsvs.accuracy import RiskTerms
from torchsvs.datasets import RecordedTracks, TrackSteps
from torchsvs.datasets.tracks import padded_batch


def centred(tracks: RecordedTracks) -> tuple[RecordedTracks, Tensor]:
    """The tracks moved so each starts near 0 (float32 keeps its resolution on large
    coordinates), and the offsets ``[B, m]`` to add back."""
    offset = tracks.z[:, 0].clone()
    if bool(torch.isnan(offset).any()):  # some track's first step misses an axis
        observed = ~torch.isnan(tracks.z)
        first = observed.to(torch.int64).argmax(dim=1, keepdim=True)  # [B, 1, m]
        offset = tracks.z.nan_to_num(0.0).gather(1, first).squeeze(1)
    return replace(tracks, z=tracks.z - offset.unsqueeze(1)), offset


class GroupBatch(NamedTuple):
    """One estimator call of ``torchsvs track``: a group of a block's tracks
    (:meth:`~torchsvs.datasets.TrackSteps.batches`), padded and moved to start near 0."""

    position: int  #: the group's position among the block's groups (seeds its random draws)
    group: np.ndarray  #: [B] int64 the group's tracks among the block's
    tracks: RecordedTracks  #: z [B, T, m] in the computation's dtype, priors not yet set
    offset: Tensor  #: [B, m] float64 what :func:`centred` took off, to add back

    def subset(self, index: Tensor) -> GroupBatch:
        """These of the group's tracks (``[k]`` int64), as a group of the same position."""
        rows = self.group[index.numpy()]
        return GroupBatch(self.position, rows, self.tracks.subset(index), self.offset[index])


class StepEstimates(NamedTuple):
    """A group's estimates at the block's flat steps, in float64: what a process hands back."""

    position: int  #: the group's position among the block's groups
    group: np.ndarray  #: [B] int64 the group's tracks among the block's
    steps: np.ndarray  #: [s] int64 the block's flat step of each estimate
    mean: np.ndarray  #: [s, 2m]
    cov: np.ndarray | None  #: [s, 2m, 2m], or None when not asked for
    never_observed: np.ndarray  #: [B, m] bool
    notes: dict[str, int]  #: :func:`~torchsvs.datasets.tracks.short_track_notes` of the group
    #: SURE's sums (:mod:`torchsvs.accuracy`), chunks' ``track`` the block's track, or None
    risk: RiskTerms | None = None
    #: [B] each track's factor on the settings' ``q`` (:func:`settings_q_factors`), or None
    q_factor: np.ndarray | None = None
    #: [o] int64 the block's flat steps set aside as outliers (:func:`screen_group`), or None
    #: where no screen ran
    outliers: np.ndarray | None = None

    @classmethod
    def merge(cls, parts: Sequence[StepEstimates], m: int) -> StepEstimates:
        """One group's estimates from those of parts of its tracks (same position)."""
        if len(parts) == 1:
            return parts[0]
        notes: Counter[str] = Counter()
        for part in parts:
            notes.update(part.notes)
        covs = [p.cov for p in parts]
        risks = [p.risk for p in parts if p.risk is not None]
        return cls(
            parts[0].position,
            np.concatenate([p.group for p in parts]),
            np.concatenate([p.steps for p in parts]),
            np.concatenate([p.mean for p in parts]),
            None if any(c is None for c in covs) else np.concatenate(covs),  # type: ignore[arg-type]
            np.concatenate([p.never_observed for p in parts]),
            dict(notes),
            RiskTerms.concat(risks, m) if len(risks) == len(parts) else None,
            None
            if all(p.q_factor is None for p in parts)
            else np.concatenate(
                [np.full(len(p.group), np.nan) if p.q_factor is None else p.q_factor for p in parts]
            ),
            None
            if all(p.outliers is None for p in parts)
            else np.concatenate([p.outliers for p in parts if p.outliers is not None]),
        )


def group_batch(
    steps: TrackSteps, group: np.ndarray, position: int, dtype: torch.dtype
) -> GroupBatch:
    """The tracks ``group`` (the block's group number ``position``) padded (float64, so the
    offsets are exact), centred, then cast to ``dtype``."""
    tracks, offset = centred(padded_batch(steps, group, torch.float64))
    return GroupBatch(position, group, tracks.to(dtype), offset)


def without_still(found: StepEstimates, batch: GroupBatch) -> StepEstimates:
    """``found`` without the error estimate's terms of the tracks that repeat one position
    throughout (:func:`~torchsvs.datasets.noise_estimate.changing_tracks`; ``batch`` centred,
    as :func:`group_batch` makes it), counted in its notes
    (``tracks_still``): their estimate is that position, and SURE at the file's noise, with no
    residual left, counted minus the noise for each (40% of a file's tracks took its error
    estimate below zero)."""
    z = batch.tracks.z  # (centred: a still track's every position is its first, 0 exactly)
    still = ~(z.reshape(len(z), -1).abs() > 0).any(1)  # (NaN > 0: False; one long axis)
    if not bool(still.any()):
        return found
    notes = dict(found.notes)
    notes["tracks_still"] = notes.get("tracks_still", 0) + int(still.sum())
    risk = found.risk
    if risk is not None:
        risk = risk.select(~np.isin(risk.track, batch.group[still.numpy()]))
    return found._replace(notes=notes, risk=risk)
