"""Shared test helpers: one assert_close, seeded random linear systems."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest
import torch

import torchsvs as ts


def assert_close(actual, expected, atol: float = 1e-9, rtol: float = 1e-9, msg: str = "") -> None:
    """The one comparison used by every test: tensors or arrays, compared in float64."""
    a = actual.detach().cpu().double().numpy() if isinstance(actual, torch.Tensor) else actual
    e = expected.detach().cpu().double().numpy() if isinstance(expected, torch.Tensor) else expected
    np.testing.assert_allclose(a, e, atol=atol, rtol=rtol, err_msg=msg)


class System(NamedTuple):
    F: np.ndarray
    H: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    x0: np.ndarray
    P0: np.ndarray
    z: np.ndarray  # [B, T, m]

    def model(self) -> ts.models.LinearGaussian:
        t = torch.from_numpy
        return ts.models.LinearGaussian(t(self.F), t(self.H), t(self.Q), t(self.R)).double()

    def tensors(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return torch.from_numpy(self.z), torch.from_numpy(self.x0), torch.from_numpy(self.P0)


def _spd(rng: np.random.Generator, d: int, scale: float) -> np.ndarray:
    A = rng.normal(size=(d, d))
    return scale * (A @ A.T / d + 0.5 * np.eye(d))


def random_system(n: int, m: int, T: int = 25, B: int = 3, seed: int = 0) -> System:
    """A random, mildly unstable linear-Gaussian system simulated with noise (float64)."""
    rng = np.random.default_rng(seed)
    F = np.eye(n) + 0.15 * rng.normal(size=(n, n))
    H = rng.normal(size=(m, n))
    Q, R = _spd(rng, n, 0.3), _spd(rng, m, 1.0)
    x0, P0 = rng.normal(size=n), _spd(rng, n, 2.0)
    z = np.empty((B, T, m))
    for b in range(B):
        x = x0 + np.linalg.cholesky(P0) @ rng.normal(size=n)
        for t in range(T):
            x = F @ x + np.linalg.cholesky(Q) @ rng.normal(size=n)
            z[b, t] = H @ x + np.linalg.cholesky(R) @ rng.normal(size=m)
    return System(F, H, Q, R, x0, P0, z)


SHAPES = [(2, 1), (3, 3), (4, 2), (5, 3)]


@pytest.fixture(params=SHAPES, ids=[f"n{n}m{m}" for n, m in SHAPES])
def system(request) -> System:
    n, m = request.param
    return random_system(n, m, seed=10 * n + m)


def atc_batch(num_runs: int = 4, seed: int = 0, dtype=torch.float64) -> ts.scenarios.Scenario:
    return ts.scenarios.atc_scenario(num_runs, torch.Generator().manual_seed(seed), dtype=dtype)


def simulate_cv(
    dt: torch.Tensor, q: float, r: float, generator: torch.Generator, speed: float = 0.0
) -> tuple[torch.Tensor, torch.Tensor]:
    """Tracks of the nearly-constant-velocity model itself (2 axes) at per-step intervals
    ``dt [B, T]``: truth ``[B, T, 4]`` and measurements ``[B, T, 2]`` (float64)."""
    B, T = dt.shape
    model = ts.models.ConstantVelocity(q=q, r=r).double()
    F, Q = model.transition(dt), model.process_noise(dt)
    x = torch.zeros(B, 4, dtype=torch.float64)
    x[:, [1, 3]] = speed * torch.randn(B, 2, generator=generator, dtype=torch.float64)
    states = []
    for t in range(T):
        w = torch.randn(B, 4, 1, generator=generator, dtype=torch.float64)
        x = (F[:, t] @ x.unsqueeze(-1) + torch.linalg.cholesky(Q[:, t]) @ w).squeeze(-1)
        states.append(x)
    truth = torch.stack(states, 1)
    noise = r**0.5 * torch.randn(B, T, 2, generator=generator, dtype=torch.float64)
    return truth, truth[..., [0, 2]] + noise


def pytest_configure(config: pytest.Config) -> None:
    """Before any test (and, under pytest-xdist, in the controller before its workers start):
    the compiled loops' library built once, so that the workers load it from the cache rather
    than each build it on a fresh machine. Each worker then runs its tests on one intra-op
    thread: two workers share the two cores, and tests that need threads set them."""
    if hasattr(config, "workerinput"):
        torch.set_num_threads(1)
        return
    from torchsvs.kernels import build

    build.library()
