"""The scenarios of Gadsden, Habibi, Kirubarajan 2012 (the SPVSF paper), as seeded batches."""

from __future__ import annotations

import torch

from torchsvs.models.ballistic import BallisticReentry
from torchsvs.models.eha import ElectrohydrostaticActuator
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

    The model has no ground: with process noise, some runs pass altitude 0 in the last seconds
    (17 of 100 seeded runs, from 26 s on) and go on falling. 30 s is the shortest duration the
    paper's RMSEs allow: they include the 6100 m initial error, ``6100/√(T+1) ≤ 360`` m needs
    ``T ≥ 286`` steps.
    """
    model = BallisticReentry().to(dtype)
    steps = round(duration / model.dt)
    Q = model.process_noise().to(dtype)
    x0 = torch.tensor([61000.0, 3048.0, 19161.0], dtype=dtype)
    # Steps ending after gravity_error_at move with the wrong-gravity truth (same Q).
    nominal = steps
    if gravity_error_at is not None:
        late = (k for k in range(steps) if (k + 1) * model.dt > gravity_error_at + 1e-9)
        nominal = next(late, steps)
    truth = model.propagate(x0.expand(num_runs, 3), nominal, generator)
    if nominal < steps:
        true_model = BallisticReentry(gravity=2.0 * model.gravity).to(dtype)
        start = truth[:, -1] if nominal else x0.expand(num_runs, 3)
        rest = true_model.propagate(start, steps - nominal, generator, cov=Q)
        truth = torch.cat([truth, rest], dim=1)
    z = model.observe(truth, generator)
    return Scenario(truth, z, model, 1.1 * x0, 10.0 * Q, model.dt)


#: Sec. 5.2's changing bulk modulus: (time from which it holds, value in Pa).
CHANGING_MODULUS = ((0.0, 2.1e8), (0.5, 1.5e8), (1.0, 2.7e8), (1.5, 2.1e8))


def eha_scenario(
    num_runs: int = 20,
    generator: torch.Generator | None = None,
    changing: bool = False,
    duration: float = 2.0,
    noise_scale: float = 1.0,
    dtype: torch.dtype = torch.float64,
) -> Scenario:
    """The EHA experiment of Sec. 5.2: random normal input, all kinematic states measured.

    The truth starts at rest with ``β_e = 2.1·10⁸`` Pa (constant, or :data:`CHANGING_MODULUS`
    with ``changing=True``) and moves under ``u ~ N(0, 1)`` with the model's kinematic process
    noise (the true modulus has no noise); the filters start from ``[0, 0, 0, 1.5·10⁸]`` with
    ``P0 = 10 Q`` (Eq. (57)). ``duration`` (s) is not stated in the text; the modulus changes
    every 0.5 s up to 1.5 s, so 2 s covers them. The inputs are returned in ``Scenario.u``.

    The paper gives the noises as "maximum amplitudes" ``W_max``, ``V_max`` and the filters' Q, R
    as ``5 W Wᵀ``, ``5 V Vᵀ`` (Eqs. (58)-(59)); by default the truth's noise has the filters'
    covariances. ``noise_scale`` multiplies the truth's kinematic process and measurement noise
    standard deviations only (the filters keep Q and R): ``1/(3√5)`` makes ``V_max`` three
    standard deviations.
    """
    if not noise_scale > 0:
        raise ValueError(f"noise_scale: expected a positive number, got {noise_scale!r}")
    model = ElectrohydrostaticActuator().to(dtype)
    steps = round(duration / model.dt)
    Q = model.process_noise().to(dtype)
    kinematic = Q.clone()
    kinematic[3, :] = kinematic[:, 3] = 0.0  # the true modulus has no process noise
    u = torch.randn(num_runs, steps, 1, generator=generator, dtype=dtype)
    schedule = CHANGING_MODULUS if changing else CHANGING_MODULUS[:1]
    # The modulus of each step's truth; a step's dynamics use the previous step's.
    modulus = [
        [value for start, value in schedule if (k + 1) * model.dt >= start - 1e-12][-1]
        for k in range(steps)
    ]
    used = [schedule[0][1], *modulus[:-1]]
    x = torch.zeros(num_runs, 4, dtype=dtype)
    x[:, 3] = schedule[0][1]
    parts = []
    k = 0
    while k < steps:  # runs of steps whose dynamics share one modulus
        end = k + 1
        while end < steps and used[end] == used[k]:
            end += 1
        part = model.propagate(
            x, end - k, generator, u=u[:, k:end], cov=kinematic, noise_scale=noise_scale
        ).clone()
        part[:, :, 3] = torch.tensor(modulus[k:end], dtype=dtype)
        parts.append(part)
        x = part[:, -1]
        k = end
    truth = torch.cat(parts, dim=1)
    z = model.observe(truth, generator, noise_scale=noise_scale)
    x0 = torch.tensor([0.0, 0.0, 0.0, 1.5e8], dtype=dtype)
    return Scenario(truth, z, model, x0, 10.0 * Q, model.dt, u=u)
