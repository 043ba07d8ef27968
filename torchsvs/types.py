"""Shape conventions, the checked inputs of a call and the result types shared by all estimators.

Batch first, one convention everywhere (column-vector math, ``F @ x``):

==================  =====================  =============================================
name                shape                  meaning
==================  =====================  =============================================
``z``               ``[B, T, m]``          measurements; NaN marks a missing component
``x0``, ``P0``      ``[B, n]``, ``[B,n,n]``  prior one step before ``z[:, 0]``
``mean``            ``[B, T, n]``          estimate after ``z[:, t]``
``cov``             ``[B, T, n, n]``       its covariance
``dt``              scalar or ``[B, T]``   interval ending at step ``t``
``psi`` override    ``[B, T, m]``          per-step boundary layer of an SVSF
==================  =====================  =============================================

A single track may be passed without the batch axis (``z [T, m]``); results then drop it too.
Model matrices stored in a result (``transition``, ``meas_matrix``, ``meas_cov``) keep size-1
axes for what does not vary: ``[1, 1, n, n]`` for a constant ``F``, ``[B, T, n, n]`` when ``dt``
varies per step.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, NamedTuple

import torch
from torch import Tensor


class FilterResult(NamedTuple):
    """What a Gaussian filter pass produced, enough for any smoother to run without re-filtering.

    A call with ``keep="moments"`` (or ``"mean"``) keeps only ``mean`` and ``cov`` (or
    ``mean``) of each step, and the log-likelihood: the other fields are ``None``
    (:data:`torchsvs.estimator.KEEP`).

    Attributes:
        mean: filtered mean ``x̂_{t|t}``, ``[B, T, n]``.
        cov: filtered covariance ``P_{t|t}``, ``[B, T, n, n]``.
        pred_mean: predicted mean ``x̂_{t|t-1}``, ``[B, T, n]``.
        pred_cov: predicted covariance ``P_{t|t-1}``, ``[B, T, n, n]``.
        innovation: a-priori innovation ``e_{t|t-1} = z_t − H x̂_{t|t-1}``, ``[B, T, m]``, 0 where
            the measurement is missing.
        mask: ``True`` where ``z`` was observed, ``[B, T, m]``.
        transition: ``F_t`` used to predict into step ``t``, ``[B|1, T|1, n, n]``.
        meas_matrix: ``H`` used by the corrector, ``[B|1, T|1, m, n]``.
        meas_cov: ``R`` used by the corrector, ``[B|1, T|1, m, m]``.
        gain: the gain the corrector applied, ``x̂_{t|t} = x̂_{t|t-1} + K_t e_t``, ``[B, T, n, m]``
            (zero columns where missing); smoothers need it for the exact error covariance.
        post_innovation: a-posteriori innovation ``e_{t|t}``, ``[B, T, m]`` (the SVSF memory;
            carried over missing components). ``None`` for filters that do not form it.
        innovation_cov: ``S_t = H P_{t|t-1} Hᵀ + R``, ``[B, T, m, m]``, identity rows/columns
            where missing; every Gaussian filter records it (the RSTKF its nominal ``S``, before
            the variational reweighting), so losses and smoothers never rebuild it.
        log_likelihood: ``Σ_t log N(e_t; 0, S_t)`` over observed components, ``[B]``, or ``None``.
        axes: the same pass per axis (:class:`~torchsvs.kernels.axes.AxisResult`) when the
            per-axis kernel computed it, so smoothers use it too; ``None`` otherwise (and in
            results of a single track without the batch axis).
    """

    mean: Tensor
    cov: Tensor
    pred_mean: Tensor
    pred_cov: Tensor
    innovation: Tensor
    mask: Tensor
    transition: Tensor
    meas_matrix: Tensor
    meas_cov: Tensor
    gain: Tensor
    post_innovation: Tensor | None = None
    innovation_cov: Tensor | None = None
    log_likelihood: Tensor | None = None
    axes: Any = None


class FilterState(NamedTuple):
    """Everything a Gaussian filter's next step needs (``est.init``, ``est.step``, ``est.scan``):
    a carry, never stored on the module.

    Attributes:
        mean: the filtered mean after the last step (or the prior), ``[B, n]``.
        cov: its covariance, ``[B|1, n, n]``.
        post_innovation: the corrector's last a-posteriori innovation (the SVSF's memory
            ``e_{k|k}``), ``[B, m']``; ``None`` before the first step and for filters that do
            not carry one.
        log_likelihood: running ``Σ log N(e_t; 0, S_t)`` since ``init``, ``[B]``, for filters
            that form it (else ``None``).
        history: what the corrector's measurement needs of earlier steps (an artificial
            measurement's raw rows), or ``None``.
        steps: steps taken since ``init``.
        single: ``init`` was given one track without the batch axis (results drop it too).
        constants: what compiled online steps computed once for the run (the model's matrices
            and the corrector's settings, rebuilt when a parameter, buffer or setting of the
            filter or its model changes), or ``None``.
        factor: ``cov`` in the filter's factored ``covariance_form``
            (:class:`torchsvs.filters.factored.Carried`), so that a run in chunks equals the
            whole run; ``None`` for the Joseph form (a state without it is factored anew).
    """

    mean: Tensor
    cov: Tensor
    post_innovation: Tensor | None = None
    log_likelihood: Tensor | None = None
    history: Any = None
    steps: int = 0
    single: bool = False
    constants: Any = None
    factor: Any = None


class SmootherResult(NamedTuple):
    """A smoothed pass and the filter pass it was computed from.

    Attributes:
        mean: smoothed mean, ``[B, T, n]``: ``x̂_{t|t+L}`` for lag ``L``, ``x̂_{t|T}`` for a fixed
            interval.
        cov: its covariance, ``[B, T, n, n]``.
        filtered: the :class:`FilterResult` of the forward pass.
    """

    mean: Tensor
    cov: Tensor
    filtered: FilterResult


@dataclass
class Inputs:
    """Checked, batched inputs of one call (``B`` tracks, ``T`` steps)."""

    z: Tensor  #: [B, T, m], NaN where missing
    x0: Tensor  #: [B, n]
    P0: Tensor  #: [B, n, n], or [1, n, n] when shared by every track
    dt: Tensor | None  #: None (model's own), 0-d, or [B, T]
    u: Tensor | None  #: control inputs [B, T, p] for models that take them
    psi: Tensor | None  #: per-step boundary layer override [B, T, m'] (checked by the SVSF)
    generator: torch.Generator | None
    single: bool  #: the caller passed one track without the batch axis
    keep: str = "all"  #: what the result keeps of each step (:data:`KEEP`)

    @property
    def batch(self) -> int:
        return self.z.shape[0]

    @property
    def steps(self) -> int:
        return self.z.shape[1]

    def window(self, start: int, stop: int) -> Inputs:
        """Steps ``start`` to ``stop - 1`` as inputs of their own (views, no copies)."""

        def span(x: Tensor | None) -> Tensor | None:
            return x[:, start:stop] if x is not None and x.ndim >= 2 else x

        return replace(
            self, z=self.z[:, start:stop], dt=span(self.dt), u=span(self.u), psi=span(self.psi)
        )
