"""The scenarios of Gadsden, Habibi, Kirubarajan 2012 (the SPVSF paper), as seeded batches."""

from __future__ import annotations

import torch

from torchsvs.models.ballistic import BallisticReentry
from torchsvs.scenarios.paper import Scenario


def ballistic_scenario(
    num_runs: int = 100,
    generator: torch.Generator | None = None,
    duration: float = 30.0,
    gravity_error_at: float | None = None,
    dtype: torch.dtype = torch.float64,
) -> Scenario:
    """Ballistic re-entry, Sec. 5.1: truth from Eq. (40) with process noise, radar measurements.

    Starts at ``[61000 m, 3048 m/s, 19161]`` (the paper's digit groups are thousands); the object
    reaches the ground after about 34 s, so ``duration`` defaults to 30 s (300 steps of 0.1 s;
    the text does not state it). The filters' prior is 10% away from the truth (``x̂0 = 1.1 x0``)
    with ``P0 = 10 Q``. With ``gravity_error_at`` (s), the truth's gravity coefficient ``g``
    doubles from that time on (in the gravity term and in the drag of Eq. (43), where it also
    appears) while the filters' model keeps ``g = 9.81`` (the modeling error of Table 2, at 15 s).
    """
    model = BallisticReentry().to(dtype)
    steps = round(duration / model.dt)
    Q, R = model.process_noise().to(dtype), model.meas_cov().to(dtype)
    LQ, LR = torch.linalg.cholesky(Q), torch.linalg.cholesky(R)
    true_model = BallisticReentry(gravity=2.0 * model.gravity).to(dtype)
    x0 = torch.tensor([61000.0, 3048.0, 19161.0], dtype=dtype)
    x = x0.expand(num_runs, 3)
    states = []
    for k in range(steps):
        late = gravity_error_at is not None and (k + 1) * model.dt > gravity_error_at + 1e-9
        x = (true_model if late else model).f(x)
        x = x + torch.randn(num_runs, 3, generator=generator, dtype=dtype) @ LQ.mT
        states.append(x)
    truth = torch.stack(states, dim=1)
    z = model.h(truth) + torch.randn(num_runs, steps, 2, generator=generator, dtype=dtype) @ LR.mT
    return Scenario(truth, z, model, 1.1 * x0, 10.0 * Q, model.dt)  # type: ignore[arg-type]
