"""The IMM's common state: where each mode's state components sit in it (:class:`Embedding`,
with the index maps mixing and combining use) and the common state as the input checks see it
(:class:`ModeSet`). Modes of different state sizes, e.g. a constant-velocity mode inside a
constant-acceleration one, are mixed without bias (Yuan et al. 2012): a mode lends the
components it lacks from the mode it is mixed into.

References:
    Yuan, Bar-Shalom, Willett, Mozeson, Pollak, Hardiman, "A multiple IMM estimation approach
    with unbiased mixing for thrusting projectiles", IEEE Trans. Aerosp. Electron. Syst. 48(4),
    2012 · Granström, Willett, Bar-Shalom, "Systematic approach to IMM mixing for unequal
    dimension states", IEEE Trans. Aerosp. Electron. Syst. 51(4), 2015.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from torchsvs.models.base import StateSpaceModel


class ModeSet(StateSpaceModel):
    """The IMM's common state as the input checks see it: its size ``n``, the measurement size
    ``m`` shared by the modes, whether ``dt`` and ``u`` apply. It has no dynamics of its own:
    each mode's model has them."""

    def __init__(self, state_dim: int, meas_dim: int, uses_dt: bool, input_dim: int) -> None:
        super().__init__()
        self.state_dim, self.meas_dim = state_dim, meas_dim
        self.uses_dt, self.input_dim = uses_dt, input_dim


class Embedding:
    """Where each mode's state components sit in the common state (``index[j][k]``: the common
    component of mode ``j``'s component ``k``), and the index maps mixing and combining use."""

    def __init__(self, index: list[list[int]], size: int) -> None:
        self.index = [torch.tensor(ix, dtype=torch.long) for ix in index]
        self.size = size
        self.identity = all(ix == list(range(size)) for ix in index)
        position = []
        for ix in index:
            where = torch.full((size,), -1, dtype=torch.long)
            where[torch.tensor(ix, dtype=torch.long)] = torch.arange(len(ix))
            position.append(where)
        #: source[i][j]: position in mode i of each component of mode j (-1: mode i lacks it)
        self.source = [
            [position[i][self.index[j]] for j in range(len(index))] for i in range(len(index))
        ]

    @classmethod
    def of(cls, embedding: Any, sizes: list[int]) -> Embedding:
        """Checks ``embedding`` (``None``: identity, for modes of one state size) against the
        modes' state sizes."""
        M = len(sizes)
        example = (
            "e.g. [[0, 1, 3, 4], [0, 1, 2, 3, 4, 5]] for ConstantVelocity and ConstantAcceleration"
        )
        if embedding is None:
            if len(set(sizes)) != 1:
                raise ValueError(
                    f"embedding: the modes' state sizes differ ({sizes}); pass, for each mode, the "
                    f"common-state index of each of its components ({example})"
                )
            return cls([list(range(sizes[0]))] * M, sizes[0])
        if isinstance(embedding, (str, bytes)) or not isinstance(embedding, Sequence):
            raise TypeError(
                "embedding: expected one sequence of indices per mode, got "
                f"{type(embedding).__name__}"
            )
        if len(embedding) != M:
            raise ValueError(
                f"embedding: expected {M} index lists (one per mode), got {len(embedding)}"
            )
        index: list[list[int]] = []
        for j, (ix, n) in enumerate(zip(embedding, sizes, strict=True)):
            values = ix.tolist() if isinstance(ix, Tensor) else ix
            if (
                isinstance(values, (str, bytes))
                or not isinstance(values, Sequence)
                or not all(isinstance(v, int) and not isinstance(v, bool) for v in values)
            ):
                raise TypeError(f"embedding: mode {j}: expected a sequence of integers, got {ix!r}")
            if len(values) != n or len(set(values)) != n or min(values, default=0) < 0:
                raise ValueError(
                    f"embedding: mode {j}: expected {n} distinct indices >= 0 (its state size), "
                    f"got {list(values)}"
                )
            index.append(list(values))
        size = max(max(ix) for ix in index) + 1
        covered = set().union(*map(set, index))
        if covered != set(range(size)):
            missing = sorted(set(range(size)) - covered)
            raise ValueError(
                f"embedding: common components {missing} belong to no mode; number the common "
                f"state 0..n-1 without gaps"
            )
        return cls(index, size)

    def into(
        self, i: int, j: int, x_i: Tensor, P_i: Tensor, x_j: Tensor, P_j: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Mode ``i``'s moments in mode ``j``'s space: the components mode ``i`` lacks take mode
        ``j``'s own mean and variance (uncorrelated with the rest), Yuan et al. 2012."""
        if i == j:
            return x_i, P_i
        src = self.source[i][j]
        has = src >= 0
        at = src.clamp_min(0)
        x = torch.where(has, x_i[..., at], x_j)
        both = has[:, None] & has[None, :]
        neither = ~has[:, None] & ~has[None, :]
        P_from_i = P_i[..., at, :][..., :, at]
        P = torch.where(both, P_from_i, torch.where(neither, P_j, torch.zeros_like(P_j)))
        return x, P

    def columns(self, j: int, l: int, P_j: Tensor) -> Tensor:
        """``Cov(x^j, x̃)`` of mode ``j``'s state with itself padded into mode ``l``'s space
        (:meth:`into`): the columns of ``P_j`` at mode ``l``'s components, zero where mode ``j``
        lacks them (the padding is uncorrelated), ``[..., n_j, n_l]``."""
        if j == l:
            return P_j
        src = self.source[j][l]
        return torch.where(
            src >= 0, P_j[..., :, src.clamp_min(0)], torch.zeros((), dtype=P_j.dtype)
        )

    def common(self, j: int, x: Tensor, P: Tensor) -> tuple[Tensor, Tensor]:
        """Mode ``j``'s moments in the common state, zero where mode ``j`` has no component."""
        if self.identity:
            return x, P
        ix, n = self.index[j], self.size
        X = x.new_zeros(*x.shape[:-1], n).index_copy(-1, ix, x)
        rows = P.new_zeros(*P.shape[:-1], n).index_copy(-1, ix, P)
        return X, P.new_zeros(*P.shape[:-2], n, n).index_copy(-2, ix, rows)

    @functools.cached_property
    def _maps(self) -> _PoolMaps:
        return _PoolMaps([ix.tolist() for ix in self.index], self.size)

    def lent(self, means: Sequence[Tensor], covs: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
        """Every mode ``i``'s moments in every mode ``j``'s space at once (:meth:`into`), each
        laid out in the common state: ``[..., i, j, n]`` and ``[..., i, j, n, n]`` from each
        mode's ``[..., n_j]``, ``[..., n_j, n_j]`` (of one leading shape); the components mode
        ``j`` lacks are 0 (:meth:`of_modes` reads mode ``j``'s own components back)."""
        maps, n, M = self._maps, self.size, len(self.index)
        return (
            _pool(means, 1).index_select(-1, maps.lent_mean).unflatten(-1, (M, M, n)),
            _pool(covs, 2).index_select(-1, maps.lent_cov).unflatten(-1, (M, M, n, n)),
        )

    def of_modes(self, x: Tensor, P: Tensor) -> list[tuple[Tensor, Tensor]]:
        """Each mode ``j``'s own components of ``x [..., j, n]``, ``P [..., j, n, n]`` (moments
        per mode laid out in the common state, as :meth:`lent` lays them out): ``(x_j [...,
        n_j], P_j [..., n_j, n_j])`` per mode."""
        maps = self._maps
        x, P = x.flatten(-2), P.flatten(-3)
        return [
            (x.index_select(-1, at_x), P.index_select(-1, at_P).unflatten(-1, (len(ix), len(ix))))
            for ix, at_x, at_P in zip(self.index, maps.own_mean, maps.own_cov, strict=True)
        ]

    def common_means(self, means: Sequence[Tensor]) -> Tensor:
        """Every mode's mean in the common state at once (:meth:`common`): ``[..., M, n]``
        from each mode's ``[..., n_j]`` (of one leading shape)."""
        M, n = len(self.index), self.size
        return _pool(means, 1).index_select(-1, self._maps.common_mean).unflatten(-1, (M, n))

    def common_covs(self, covs: Sequence[Tensor]) -> Tensor:
        """Every mode's covariance in the common state at once (:meth:`common`):
        ``[..., M, n, n]`` from each mode's ``[..., n_j, n_j]`` (of one leading shape)."""
        M, n = len(self.index), self.size
        return _pool(covs, 2).index_select(-1, self._maps.common_cov).unflatten(-1, (M, n, n))

    def project(self, j: int, x: Tensor, P: Tensor) -> tuple[Tensor, Tensor]:
        """The components of mode ``j`` of a common-state ``x``, ``P``."""
        if self.identity:
            return x, P
        ix = self.index[j]
        return x[..., ix], P[..., ix, :][..., :, ix]


def _pool(parts: Sequence[Tensor], rank: int) -> Tensor:
    """Every mode's vector (``rank`` 1) or matrix (2) flattened and concatenated, then a 0:
    ``[..., Σ n_j (+ 1)]`` or ``[..., Σ n_j² (+ 1)]``, what :class:`_PoolMaps` gathers from."""
    flat = [p.flatten(-rank) for p in parts]
    return torch.cat([*flat, flat[0].new_zeros(*flat[0].shape[:-1], 1)], -1)


class _PoolMaps:
    """Gather maps over a pool of every mode's moments (the means concatenated ``[Σ n_j]``, then
    a 0; the covariances flattened and concatenated ``[Σ n_j²]``, then a 0): the moments of
    :meth:`Embedding.lent`, :meth:`Embedding.of_modes` and :meth:`Embedding.commons` in one
    gather each, every entry a copy of a mode's entry or 0."""

    def __init__(self, index: list[list[int]], size: int) -> None:
        M, n = len(index), size
        sizes = [len(ix) for ix in index]
        start_x = [sum(sizes[:j]) for j in range(M)]
        start_P = [sum(k * k for k in sizes[:j]) for j in range(M)]
        zero_x, zero_P = sum(sizes), sum(k * k for k in sizes)
        where = [{c: k for k, c in enumerate(ix)} for ix in index]  # common -> position in mode

        def mean_at(j: int, c: int) -> int:
            return start_x[j] + where[j][c]

        def cov_at(j: int, a: int, b: int) -> int:
            return start_P[j] + where[j][a] * sizes[j] + where[j][b]

        lent_mean = torch.full((M, M, n), zero_x, dtype=torch.long)
        lent_cov = torch.full((M, M, n, n), zero_P, dtype=torch.long)
        for i in range(M):
            for j in range(M):
                for a in index[j]:
                    # a component mode i lacks: mode j's own (Embedding.into)
                    lent_mean[i, j, a] = mean_at(i if a in where[i] else j, a)
                    for b in index[j]:
                        if a in where[i] and b in where[i]:
                            lent_cov[i, j, a, b] = cov_at(i, a, b)
                        elif a not in where[i] and b not in where[i]:
                            lent_cov[i, j, a, b] = cov_at(j, a, b)
        self.lent_mean, self.lent_cov = lent_mean.flatten(), lent_cov.flatten()
        common_mean = torch.full((M, n), zero_x, dtype=torch.long)
        common_cov = torch.full((M, n, n), zero_P, dtype=torch.long)
        for j in range(M):
            for a in index[j]:
                common_mean[j, a] = mean_at(j, a)
                for b in index[j]:
                    common_cov[j, a, b] = cov_at(j, a, b)
        self.common_mean, self.common_cov = common_mean.flatten(), common_cov.flatten()
        ix = [torch.tensor(i, dtype=torch.long) for i in index]
        self.own_mean = [j * n + ix[j] for j in range(M)]
        self.own_cov = [
            j * n * n + (ix[j][:, None] * n + ix[j][None, :]).flatten() for j in range(M)
        ]
