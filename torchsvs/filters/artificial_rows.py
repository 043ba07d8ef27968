"""An artificial measurement over a run taken in chunks: which one ``artificial="auto"``
picks, and the raw rows it reads back to, carried in the filter's state between chunks so that
a run in chunks (or step by step) forms the measurements of the whole run
(:class:`~torchsvs.filters.SVSF`, :class:`~torchsvs.filters.ArtificialKalmanFilter`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple, cast

import torch
from torch import Tensor

from torchsvs.estimator import Inputs
from torchsvs.filters.adaptive import AdaptiveNoise
from torchsvs.filters.artificial import FiniteDifferenceVelocity
from torchsvs.models.base import StateSpaceModel

ArtificialMeasurement = Callable[
    [Tensor, StateSpaceModel, "Tensor | None", "Tensor | None"], tuple[Tensor, Tensor, Tensor]
]


def auto_artificial(model: StateSpaceModel) -> ArtificialMeasurement | None:
    """The artificial measurement ``artificial="auto"`` picks: finite-difference velocity for a
    model whose measurement is its positions and whose state adds their velocities, else none."""
    pos = getattr(model, "position_index", None)
    vel = getattr(model, "velocity_index", None)
    if pos is None or vel is None or model.meas_dim >= model.state_dim:
        return None
    if len(pos) != model.meas_dim or len(set(pos) | set(vel)) != model.state_dim:
        return None
    return FiniteDifferenceVelocity()


def artificial_measurements(
    artificial: ArtificialMeasurement,
    model: StateSpaceModel,
    history: Any,
    inputs: Inputs,
    adaptive: AdaptiveNoise | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """The artificial measurement of the steps of ``inputs``, ``H`` and ``R``, formed over the
    rows kept from earlier steps and these (see :func:`rows_to_keep`); with ``adaptive``, from
    the adaptive ``R_k`` of those rows."""
    window = _window(history, inputs)
    if adaptive is None:
        z, H, R = artificial(window.z, model, window.dt, window.u)
    else:  # the kept rows cover the segments of this call's steps (carried_history)
        R_k = adaptive.covariance(model.meas_cov().to(window.z.dtype), window.z)
        z, H, R = cast(Any, artificial)(window.z, model, window.dt, window.u, meas_cov=R_k)
    H, R = H.to(z.dtype), R.to(z.dtype)
    kept = window.z.shape[1] - inputs.steps
    return z[:, kept:], H, R[:, kept:] if R.ndim == 4 else R


def rows_to_keep(history: Any, inputs: Inputs, at_least: int = 1, reach_back: int = 0) -> Rows:
    """The raw rows an artificial measurement may still look back to: from the earliest step at
    which some track last observed some component (finite differences bridge gaps back to it),
    and ``reach_back`` rows before it (the segments of its adaptive ``R_k``), and at least the
    last ``at_least`` rows (a step's previous row)."""
    window = _window(history, inputs)
    T = window.z.shape[1]
    least = max(0, T - at_least)
    if not bool(torch.isnan(window.z[:, -1]).any()):  # every component seen last step
        return _window_rows(window, max(0, min(T - 1 - reach_back, least)))
    seen = ~torch.isnan(window.z)
    index = torch.arange(T).view(1, T, 1).expand_as(seen)
    last = torch.where(seen, index, torch.full_like(index, -1)).amax(dim=1)  # [B, m]
    observed = last[last >= 0]
    start = min(T - 1, int(observed.min())) if observed.numel() else T - 1
    return _window_rows(window, max(0, min(start - reach_back, least)))


class Rows(NamedTuple):
    """Raw measurement rows with their intervals and inputs (``dt``: None, 0-d or ``[B, k]``)."""

    z: Tensor
    dt: Tensor | None
    u: Tensor | None


def _window(history: Rows | None, inputs: Inputs) -> Rows:
    """The kept rows of earlier steps followed by this call's."""
    if history is None:
        return Rows(inputs.z, inputs.dt, inputs.u)
    B, kept = history.z.shape[:2]
    dt: Tensor | None
    if history.dt is None and inputs.dt is None:
        dt = None
    elif history.dt is None or inputs.dt is None:
        raise ValueError(
            "dt: pass it at every step or at none (the earlier steps of this state "
            f"{'had' if history.dt is not None else 'had no'} dt)"
        )
    elif history.dt.ndim == 0 and inputs.dt.ndim == 0 and bool(history.dt == inputs.dt):
        dt = inputs.dt  # one interval throughout: kept as a scalar, as a whole run has it
    else:
        dt = torch.cat([history.dt.expand(B, kept), inputs.dt.expand(B, inputs.steps)], dim=1)
    u = None if history.u is None or inputs.u is None else torch.cat([history.u, inputs.u], 1)
    return Rows(torch.cat([history.z, inputs.z], dim=1), dt, u)


def _window_rows(window: Rows, start: int) -> Rows:
    """The rows of ``window`` from ``start`` on."""
    dt = window.dt if window.dt is None or window.dt.ndim == 0 else window.dt[:, start:]
    u = None if window.u is None else window.u[:, start:]
    return Rows(window.z[:, start:], dt, u)
