"""Random maneuvering tracks for training, as a Lightning data module."""

from __future__ import annotations

import zlib
from dataclasses import asdict
from typing import Any

import lightning as L
import torch
from torch import Tensor
from torch.utils.data import DataLoader, Dataset

from torchsvs.datasets.tracks import RecordedTracks
from torchsvs.fitting.batches import TrackBatch, recorded_batches
from torchsvs.scenarios.maneuver import ManeuverRanges
from torchsvs.scenarios.paper import random_scenario


class ManeuverDataset(Dataset[TrackBatch]):
    """``num_batches`` batches of ``batch_size`` random tracks; batch ``i`` is a pure function of
    ``(seed, split, i)``, so every split is reproducible and splits never share tracks.

    Hard cases on request: with probability ``outlier_prob`` a measurement component gets an
    extra ``outlier_scale``-σ Gaussian error; with probability ``missing_prob`` it is NaN.
    """

    def __init__(
        self,
        num_batches: int,
        batch_size: int,
        ranges: ManeuverRanges,
        prior_std: tuple[float, float],
        seed: int,
        split: str,
        outlier_prob: float = 0.0,
        outlier_scale: float = 10.0,
        missing_prob: float = 0.0,
        cached: bool = True,
        dtype: torch.dtype = torch.float32,
    ) -> None:
        self.num_batches, self.batch_size, self.ranges = num_batches, batch_size, ranges
        self.prior_std = prior_std
        self.seed = zlib.crc32(f"{seed}/{split}".encode())
        self.outlier_prob, self.outlier_scale = outlier_prob, outlier_scale
        self.missing_prob, self.dtype = missing_prob, dtype
        self._cache = [self._make(i) for i in range(num_batches)] if cached else None

    def __len__(self) -> int:
        return self.num_batches

    def __getitem__(self, index: int) -> TrackBatch:
        if not 0 <= index < self.num_batches:
            raise IndexError(index)
        return self._cache[index] if self._cache is not None else self._make(index)

    def _make(self, index: int) -> TrackBatch:
        gen = torch.Generator().manual_seed(self.seed + 7919 * index)
        sc = random_scenario(self.batch_size, self.ranges, prior_std=self.prior_std, generator=gen)
        z, x0, P0 = sc.z, sc.x0, sc.P0
        assert sc.meas_std is not None
        if self.outlier_prob > 0:
            hit = torch.rand(z.shape, generator=gen, dtype=z.dtype) < self.outlier_prob
            noise = torch.randn(z.shape, generator=gen, dtype=z.dtype)
            z = z + hit * self.outlier_scale * sc.meas_std[:, None, None] * noise
        if self.missing_prob > 0:
            gone = torch.rand(z.shape, generator=gen, dtype=z.dtype) < self.missing_prob
            z = z.masked_fill(gone, float("nan"))
        cast = self.dtype
        return TrackBatch(z.to(cast), sc.truth.to(cast), x0.to(cast), P0.to(cast))


class ManeuveringTargetDataModule(L.LightningDataModule):
    """Seeded train/val/test splits of random maneuvering tracks (batches of whole tracks).

    Args:
        ranges: the maneuver distribution (speeds, segment kinds and lengths, turn rates,
            accelerations, measurement noise, steps).
        prior_std: standard deviations ``(position, velocity)`` of the filters' prior ``P0``;
            ``x0`` is drawn from ``N(true initial state, P0)``.
        batch_size: tracks per batch.
        train_batches, val_batches, test_batches: batches per split (an epoch is
            ``train_batches`` optimiser steps).
        seed: base seed of all splits.
        cached: generate every batch once in ``setup`` (else on the fly, still reproducible).
        outlier_prob, outlier_scale, missing_prob: hard cases in the training split.
        double: float64 batches (default float32).
    """

    def __init__(
        self,
        ranges: ManeuverRanges | None = None,
        prior_std: tuple[float, float] = (100.0, 30.0),
        batch_size: int = 64,
        train_batches: int = 40,
        val_batches: int = 4,
        test_batches: int = 8,
        seed: int = 0,
        cached: bool = True,
        outlier_prob: float = 0.0,
        outlier_scale: float = 10.0,
        missing_prob: float = 0.0,
        double: bool = False,
    ) -> None:
        super().__init__()
        # Plain values only, so checkpoints load with torch.load(weights_only=True).
        self.save_hyperparameters(ignore=["ranges"])
        ranges = ranges if ranges is not None else ManeuverRanges()
        self.hparams["ranges"] = asdict(ranges)
        self.ranges, self.prior_std = ranges, tuple(prior_std)
        self.batch_size, self.seed, self.cached = batch_size, seed, cached
        self.sizes = {"train": train_batches, "val": val_batches, "test": test_batches}
        self.hard = {
            "outlier_prob": outlier_prob,
            "outlier_scale": outlier_scale,
            "missing_prob": missing_prob,
        }
        self.dtype = torch.float64 if double else torch.float32
        self.datasets: dict[str, ManeuverDataset] = {}

    def _dataset(self, split: str) -> ManeuverDataset:
        if split not in self.datasets:
            hard = self.hard if split == "train" else {}
            self.datasets[split] = ManeuverDataset(
                self.sizes[split],
                self.batch_size,
                self.ranges,
                self.prior_std,  # type: ignore[arg-type]
                self.seed,
                split,
                cached=self.cached,
                dtype=self.dtype,
                **hard,
            )
        return self.datasets[split]

    def setup(self, stage: str | None = None) -> None:
        splits = {"fit": ["train", "val"], "validate": ["val"], "test": ["test"]}
        for split in splits.get(stage or "fit", ["train", "val", "test"]):
            self._dataset(split)

    def _loader(self, split: str, shuffle: bool = False) -> DataLoader:
        gen = torch.Generator().manual_seed(self.seed) if shuffle else None
        return DataLoader(
            self._dataset(split),
            batch_size=None,
            shuffle=shuffle,
            generator=gen,
            collate_fn=_identity,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val")

    def test_dataloader(self) -> DataLoader:
        return self._loader("test")


def _identity(batch: Any) -> Any:
    return batch


class RecordedTracksDataModule(L.LightningDataModule):
    """A fixed set of recorded tracks, split by track into training and validation, cut into
    windows (needs no truth; RMSE is logged where the tracks carry ``truth``).

    Args:
        tracks: the tracks (e.g. from :func:`~torchsvs.datasets.read_tracks`).
        meas_std: the sensor's noise standard deviation (a number or one per axis) for the
            priors and for SURE; ``None`` estimates it from the training tracks
            (:func:`~torchsvs.datasets.estimate_noise`).
        val_fraction: share of the tracks held out for validation (at least one when there
            are two or more).
        window, burn_in: window length and overlap (see :func:`recorded_batches`).
        batch_size: windows per batch.
        seed: of the split and of the shuffling.
        double: float64 batches (default float32).
    """

    def __init__(
        self,
        tracks: RecordedTracks,
        meas_std: float | list[float] | None = None,
        val_fraction: float = 0.25,
        window: int = 128,
        burn_in: int = 16,
        batch_size: int = 64,
        seed: int = 0,
        double: bool = False,
    ) -> None:
        super().__init__()
        if not 0.0 <= val_fraction < 1.0:
            raise ValueError(f"val_fraction: expected a value in [0, 1), got {val_fraction!r}")
        self.tracks, self.window, self.burn_in = tracks, window, burn_in
        self.batch_size, self.seed = batch_size, seed
        self.dtype = torch.float64 if double else torch.float32
        count = len(tracks)
        order = torch.randperm(count, generator=torch.Generator().manual_seed(seed))
        held = min(count - 1, max(1 if count >= 2 else 0, round(val_fraction * count)))
        self.val_index, self.train_index = order[:held].sort().values, order[held:].sort().values
        train = tracks.subset(self.train_index)
        if meas_std is None:
            from torchsvs.datasets import estimate_noise

            self.meas_var = estimate_noise(train.z.double(), train.dt.double()).meas_var.double()
        else:
            std = torch.as_tensor(meas_std, dtype=torch.float64).reshape(-1)
            self.meas_var = std.expand(tracks.z.shape[-1]).square()
        self.batches: dict[str, list[TrackBatch]] = {}

    @property
    def meas_cov(self) -> Tensor:
        """The measurement covariance the batches assume, ``[m, m]`` (for SURE)."""
        return torch.diag(self.meas_var)

    def setup(self, stage: str | None = None) -> None:
        for split, index in (("train", self.train_index), ("val", self.val_index)):
            if split not in self.batches and len(index):
                self.batches[split] = recorded_batches(
                    self.tracks.subset(index),
                    self.meas_var,
                    self.window,
                    self.burn_in,
                    self.batch_size,
                    self.dtype,
                )

    def train_dataloader(self) -> DataLoader:
        gen = torch.Generator().manual_seed(self.seed)
        return DataLoader(
            _Batches(self.batches["train"]),
            batch_size=None,
            shuffle=True,
            generator=gen,
            collate_fn=_identity,
        )

    def val_dataloader(self) -> DataLoader:
        return DataLoader(
            _Batches(self.batches.get("val", [])), batch_size=None, collate_fn=_identity
        )


class _Batches(Dataset[TrackBatch]):
    """Ready-made batches as a dataset (each item one batch)."""

    def __init__(self, batches: list[TrackBatch]) -> None:
        self.items = batches

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int) -> TrackBatch:
        return self.items[index]
