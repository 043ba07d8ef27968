"""The benchmarks' shared problem: the papers' 2-D constant-velocity model with position
measurements, seeded tracks, per-track priors, and the peer libraries called on the same data.

Every peer takes the prior at the first measurement and updates first (filterpy's
``batch_filter(update_first=True)``), so each is handed ``x0``, ``P0`` predicted once
(:attr:`CVProblem.first_prior`); torchsvs takes the prior one step before ``z[:, 0]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch

import torchsvs as ts


@dataclass
class CVProblem:
    """``tracks`` seeded tracks × ``steps`` steps of the constant-velocity model (``dt`` 1 s,
    ``q`` 0.16, measurement noise 200 m), all starting from ``x0``; ``z`` ``[B, T, 2]`` is float32
    (``z.double()`` holds the same numbers, so float32 and float64 runs see identical data)."""

    tracks: int
    steps: int
    seed: int = 0

    def __post_init__(self) -> None:
        self.model = self.make_model()
        self.x0 = torch.tensor([-25000.0, 120.0, -10000.0, 0.0])
        self.P0 = torch.diag(torch.tensor([1e4, 1e3, 1e4, 1e3]))
        generator = torch.Generator().manual_seed(self.seed)
        _, z = self.model.simulate(self.x0.expand(self.tracks, 4), self.steps, generator=generator)
        self.z = z.float().contiguous()
        model = self.make_model().double()
        #: ``F, H, Q, R`` as float64 arrays (from a model of their own: ``.to(dtype)`` on an
        #: estimator converts its model in place).
        self.matrices = tuple(
            m.numpy()
            for m in (
                model.transition(),
                model.meas_matrix(),
                model.process_noise(),
                model.meas_cov(),
            )
        )

    @staticmethod
    def make_model(learn_noise: bool = False) -> ts.models.ConstantVelocity:
        """A new model of the problem (its own tensors: an estimator's ``.to(dtype)``
        converts its model in place)."""
        return ts.models.ConstantVelocity(dt=1.0, q=0.16, r=200.0**2, learn_noise=learn_noise)

    def z_as(self, dtype: torch.dtype) -> torch.Tensor:
        """``z`` in ``dtype``, converted once."""
        converted = self.__dict__.setdefault("_converted", {})
        if dtype not in converted:
            converted[dtype] = self.z.to(dtype)
        return converted[dtype]

    def per_track_P0(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """``P0`` as ``[B, n, n]``: B covariance recursions, as the peers run."""
        return self.P0.to(dtype).expand(self.tracks, 4, 4).contiguous()

    @cached_property
    def first_prior(self) -> tuple[np.ndarray, np.ndarray]:
        """The prior at ``z[:, 0]`` (``x0``, ``P0`` predicted once), float64."""
        F, _, Q, _ = self.matrices
        return F @ self.x0.double().numpy(), F @ self.P0.double().numpy() @ F.T + Q

    @cached_property
    def z_numpy(self) -> np.ndarray:
        """``z`` as float64 ``[B, T, 2]``."""
        return self.z.double().numpy()


def simdkalman_run(
    problem: CVProblem, smoothed: bool = False, observations: bool = False
) -> np.ndarray:
    """simdkalman on every track, its fastest options by default (states and covariances
    only, ``observations=False``): the filtered, or the smoothed, means ``[B, T, n]``."""
    import simdkalman

    F, H, Q, R = problem.matrices
    m0, P_init = problem.first_prior
    result = simdkalman.KalmanFilter(F, Q, H, R).compute(
        problem.z_numpy,
        0,
        initial_value=m0,
        initial_covariance=P_init,
        smoothed=smoothed,
        filtered=not smoothed,
        observations=observations,
    )
    return (result.smoothed if smoothed else result.filtered).states.mean


def filterpy_run(problem: CVProblem, tracks: int, smooth: bool = False) -> np.ndarray:
    """filterpy, one track at a time (``batch_filter``, and ``rts_smoother``), on the first
    ``tracks`` tracks: the filtered or smoothed means ``[tracks, T, n]``."""
    from filterpy.kalman import KalmanFilter, rts_smoother

    F, H, Q, R = problem.matrices
    m0, P_init = problem.first_prior
    T = problem.steps
    means = []
    for track in problem.z_numpy[:tracks]:
        f = KalmanFilter(dim_x=4, dim_z=2)
        f.x, f.P, f.F, f.H, f.Q, f.R = m0.copy(), P_init.copy(), F, H, Q, R
        mu, cov, _, _ = f.batch_filter(list(track), update_first=True)
        if smooth:
            mu = rts_smoother(mu, cov, [F] * T, [Q] * T)[0]
        means.append(np.asarray(mu).reshape(T, 4))
    return np.stack(means)
