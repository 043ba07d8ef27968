"""The IMM's mode-matched steps on each mode's run prepared once: what a one-step
:meth:`~torchsvs.filters.GaussianFilter.step` of every mode at every step would compute, without
checking, preparing, stacking and trimming a run of one step each time (on recorded tracks that
was half the IMM's time per step, the steps being many small tensor operations)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

from torch import Tensor

from torchsvs.estimator import Inputs, at_step, prepare_inputs
from torchsvs.filters.gaussian import (
    GaussianFilter,
    Prepared,
    as_result_matrix,
    step_input,
    step_interval,
)
from torchsvs.kernels import compiled
from torchsvs.kernels.fused_axes import Last
from torchsvs.types import FilterResult, FilterState


def prepared_runs(filters: Sequence[GaussianFilter], inputs: Inputs) -> Runs | None:
    """Each mode's whole run prepared once (:meth:`~GaussianFilter.prepare`: measurements,
    mask, model matrices), where every mode's step can be its
    :meth:`~GaussianFilter.filter_step` on it (:func:`mode_step`); else ``None`` (each step is
    the mode's one-step :meth:`~GaussianFilter.step`). It is not taken with compiled steps,
    without an interval or input (the filters' online shortcut may take the step), for a
    filter whose corrector carries earlier rows (an artificial measurement, an adaptive ``R``)
    or a factored covariance, or which runs its steps its own way."""
    if compiled.active() or (inputs.dt is None and inputs.u is None):
        return None
    for f in filters:
        if (
            f.covariance_form != "joseph"
            or f.adaptive_noise is not None
            or any(
                getattr(type(f), name) is not getattr(GaussianFilter, name)
                for name in ("step", "scan", "_scan")
            )
            or f.carried_history(None, inputs) is not None
        ):
            return None
    for f in filters:  # the checks of each mode's own steps (its model's dt, u), once
        n = f.model.state_dim
        zeros = inputs.z.new_zeros(1, n, n)
        prepare_inputs(
            f.model, inputs.z, zeros[:, 0], zeros, u=inputs.u, dt=inputs.dt, state_prior=True
        )
    preps = [f.prepare(inputs) for f in filters]
    # per mode and step: whether anything in the batch is missing (a one-step run's mask)
    missing = [(~p.observed).any(-1).any(0).tolist() for p in preps]
    return Runs(preps, missing)


class Runs(NamedTuple):
    """Each mode's whole run prepared once (:func:`prepared_runs`)."""

    preps: list[Prepared]
    missing: list[list[bool]]  #: per mode and step: anything missing in the batch at that step


def mode_step(
    f: GaussianFilter, prior: FilterState, runs: Runs, j: int, inputs: Inputs, t: int
) -> tuple[FilterState, FilterResult]:
    """Mode ``j``'s filter ``f`` at step ``t`` from ``prior`` on its run prepared once: the
    state after it and the step's result, the same numbers and fields as its one-step
    :meth:`~GaussianFilter.step` gives (whose inputs are these steps' views: its fast path
    where the filter takes one, else :meth:`~GaussianFilter.filter_step`, the step
    :meth:`~GaussianFilter.scan` records)."""
    if prior.history is not None or prior.single:
        z_t, dt_t, u_t = inputs.z[:, t], step_interval(inputs, t), step_input(inputs, t)
        return f.step(prior, z_t, dt=dt_t, u=u_t, generator=inputs.generator)
    B, dtype = inputs.batch, inputs.z.dtype
    x, P = prior.mean.to(dtype).expand(B, -1), prior.cov.to(dtype)  # (as scan's prior)
    if type(f).fast_pass is not GaussianFilter.fast_pass:
        one = _one_step(inputs, t, x, P)
        fast = f.fast_pass(prior, one)
        if fast is not None:
            result, last = fast
            return _after(prior, result.log_likelihood, last), at_step(result, 0)
    prep = runs.preps[j]._replace(any_missing=runs.missing[j][t])
    x_pred, P_pred, F_t, step = f.filter_step(t, x, P, prior.post_innovation, prep, inputs)

    def full(v: Tensor) -> Tensor:  # a run of one step's record at that step, as scan keeps it
        return v if v.shape[0] == B else v.expand(B, *v.shape[1:])

    def at(A: Tensor) -> Tensor:  # a model matrix at step t, as a run's result keeps it
        A = as_result_matrix(A)
        return A.select(1, min(t, A.shape[1] - 1))

    ll = step.log_likelihood
    result = FilterResult(
        mean=full(step.mean),
        cov=full(step.cov),
        pred_mean=full(x_pred),
        pred_cov=full(P_pred),
        innovation=full(step.innovation),
        mask=prep.observed[:, t],
        transition=full(F_t) if prep.F is None else at(prep.F),
        meas_matrix=at(prep.H) if prep.H is not None else full(_given(step.meas_matrix)),
        meas_cov=at(prep.R),
        gain=full(step.gain),
        post_innovation=None if step.post_innovation is None else full(step.post_innovation),
        innovation_cov=None if step.innovation_cov is None else full(step.innovation_cov),
        log_likelihood=None if ll is None else full(ll).unsqueeze(1).sum(1),
    )
    last = Last(result.mean, result.cov, result.post_innovation)
    return _after(prior, result.log_likelihood, last), result


def _one_step(inputs: Inputs, t: int, x0: Tensor, P0: Tensor) -> Inputs:
    """Step ``t`` of ``inputs`` as a run of its own from ``x0``, ``P0`` (as a one-step
    :meth:`~GaussianFilter.step` checks them: views, keeping everything)."""

    def span(v: Tensor | None) -> Tensor | None:
        return v[:, t : t + 1] if v is not None and v.ndim >= 2 else v

    z, dt, u, psi = span(inputs.z), span(inputs.dt), span(inputs.u), span(inputs.psi)
    assert z is not None
    return Inputs(z, x0, P0, dt, u, psi, inputs.generator, False, "all")


def _given(value: Tensor | None) -> Tensor:
    assert value is not None, "a filter that linearises h per step reports its H"
    return value


def _after(prior: FilterState, log_likelihood: Tensor | None, last: Last) -> FilterState:
    """The filter's state after one step from ``prior`` (as its ``scan`` leaves it)."""
    if log_likelihood is not None and prior.log_likelihood is not None:
        log_likelihood = prior.log_likelihood + log_likelihood
    return FilterState(
        mean=last.mean,
        cov=last.cov,
        post_innovation=last.post_innovation,
        log_likelihood=log_likelihood,
        steps=prior.steps + 1,
        single=prior.single,
    )
