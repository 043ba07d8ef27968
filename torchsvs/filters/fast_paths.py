"""The fast paths: faster ways to the numbers of a Gaussian filter's step loop, taken where a
filter declares that its corrector has one (:class:`FastPaths`) and the problem fits.

* The per-axis kernel (:func:`torchsvs.kernels.axes.run_axes`, compiled loops in
  :mod:`torchsvs.kernels.fused_axes`): a :class:`~torchsvs.models.ConstantVelocity` whose axes
  do not couple, run as 2×2 blocks per axis, with or without gradients.
* The compiled dense steps (:func:`torchsvs.kernels.fused_dense.dense_run`): a linear model of
  at most ``fused_dense.DENSE_MAX`` states and measurements, without gradients; its constants
  (:class:`DenseConstants`) are formed once and carried in the state, and an online
  :meth:`~FastPathFilter.step` is one library call
  (:class:`torchsvs.kernels.fused_dense.OnlineStep`).

Anything else runs :class:`~torchsvs.filters.gaussian.GaussianFilter`'s step loop. Every fast
path gives the loop's numbers up to rounding (the kernel tests pin them).
"""

from __future__ import annotations

import operator
import threading
from collections.abc import Callable
from dataclasses import replace
from typing import Any, NamedTuple, cast

import torch
from torch import Tensor

from torchsvs.estimator import Inputs
from torchsvs.filters.gaussian import GaussianFilter, as_result_matrix, last_step
from torchsvs.kernels import AXIS_KERNEL, axes, blocks, build, fused_axes, fused_dense
from torchsvs.models.base import LinearModel, StateSpaceModel
from torchsvs.models.motion import ConstantVelocity
from torchsvs.types import FilterResult, FilterState


class FastPaths(NamedTuple):
    """What a filter's corrector declares it can be run as (:attr:`FastPathFilter.paths`)."""

    #: its rule in the per-axis kernel (:func:`torchsvs.kernels.axes.run_axes`): ``"kalman"``,
    #: ``"svsf"``, ``"vbl-innovation"``, ``"vbl-gain"``; None: none
    axis: str | None = None
    #: its rule in the compiled dense steps (:func:`torchsvs.kernels.fused_dense.dense_run`) for
    #: linear models: ``"kalman"``, ``"svsf"``; None: none
    dense: str | None = None


#: No fast path: the step loop runs every step.
NO_FAST_PATHS = FastPaths()


class DenseConstants(NamedTuple):
    """What a run of compiled online steps computes once (``FilterState.constants``)."""

    matrices: fused_dense.DenseMatrices  #: F, Q, H, R, contiguous, in the run's dtype
    gamma: float  #: the SVSF's γ (0 for the KF)
    widths: Tensor  #: the SVSF's ψ, [m] (zeros for the KF)
    tensors: list[Tensor]  #: the filter's and model's parameters and buffers they came from
    settings: list[str]  #: the model's plain settings (its ``dt``) they came from
    fingerprint: tuple[Any, ...]  #: :func:`_fingerprint` when they were built
    #: the compiled online steps formed so far, by (keep, leading shape, thread: each has its
    #: own scratch)
    steps: dict[tuple[Any, ...], CompiledStep]


class CompiledStep(NamedTuple):
    """A compiled online step (:class:`torchsvs.kernels.fused_dense.OnlineStep`) and how its kept
    outputs fill :class:`DenseOutputs`."""

    call: fused_dense.OnlineStep
    #: picks the :class:`DenseOutputs` fields from its kept outputs followed by a ``None``
    pick: Callable[[list[Any]], tuple[Any, ...]]

    @staticmethod
    def of(call: fused_dense.OnlineStep) -> CompiledStep:
        """``call`` and its :attr:`pick`."""
        kept = list(call.kept)
        where = [
            kept.index(i) if i in kept else len(kept) for i in range(len(DenseOutputs._fields))
        ]
        return CompiledStep(call, operator.itemgetter(*where))


class DenseOutputs(NamedTuple):
    """What the compiled dense steps write, in :func:`~torchsvs.kernels.fused_dense.dense_run`'s
    order (``None``: not kept)."""

    mean: Tensor
    cov: Tensor
    pred_mean: Tensor | None
    pred_cov: Tensor | None
    innovation: Tensor | None
    gain: Tensor | None
    innovation_cov: Tensor | None
    log_likelihood: Tensor | None  #: per step (the Kalman rule's; the SVSF's is not reported)
    post_innovation: Tensor | None  #: the SVSF's memory
    observed: Tensor | None  #: the mask


class AxisPass(NamedTuple):
    """A pass through the per-axis kernel (:meth:`FastPathFilter.axis_pass`)."""

    result: FilterResult
    last: fused_axes.Last  #: the state after its last step
    smoothed: tuple[Tensor, Tensor] | None  #: the smoothed mean and covariance asked for


def _plain_settings(model: StateSpaceModel) -> list[str]:
    return [k for k, v in vars(model).items() if isinstance(v, (bool, int, float, str))]


def _fingerprint(tensors: list[Tensor], model: StateSpaceModel, settings: list[str]) -> tuple:
    """Changes when a parameter or buffer is updated in place or given new data, a plain
    setting of the model (its ``dt``) changes, or the filter is given another model: the
    constants are then rebuilt."""
    values = model.__dict__
    return (
        id(model),
        *[(t._version, t.data_ptr()) for t in tensors],
        *[values[k] for k in settings],
    )


def _dense_result(
    out: DenseOutputs,
    rule: str,
    matrices: fused_dense.DenseMatrices,
    lead: tuple[int, ...],
    keep: str,
) -> FilterResult:
    """The result of compiled dense steps with the leading shape ``lead``: the run's ``F``,
    ``H``, ``R`` broadcast over it where ``keep`` keeps everything; the outputs not kept stay
    ``None`` (as FilterResult's doc says)."""
    kalman = rule == "kalman"
    F: Any = None
    H: Any = None
    R: Any = None
    if keep == "all":
        F, _, H, R = matrices.tensors
        if lead:  # the run's matrices, broadcast over the leading axes
            F, H, R = (A.view((1,) * len(lead) + A.shape) for A in (F, H, R))
    kept: Any = out  # (fields a result keeps are tensors)
    return FilterResult(
        mean=out.mean,
        cov=out.cov,
        pred_mean=kept.pred_mean,
        pred_cov=kept.pred_cov,
        innovation=kept.innovation,
        mask=kept.observed,
        transition=F,
        meas_matrix=H,
        meas_cov=R,
        gain=kept.gain,
        post_innovation=None if kalman else out.post_innovation,
        innovation_cov=out.innovation_cov,
        log_likelihood=out.log_likelihood if kalman else None,
    )


class FastPathFilter(GaussianFilter):
    """A :class:`~torchsvs.filters.gaussian.GaussianFilter` whose runs, smoother passes and
    online steps take the fast paths its corrector declares (:attr:`paths`) where the
    kernels can carry it (:meth:`supports`) and the problem fits; else its step loop."""

    #: the fast paths the corrector declares (a subclass declares its own)
    paths: FastPaths = NO_FAST_PATHS

    def supports(self) -> FastPaths:
        """The fast paths that may run this filter: its declared :attr:`paths` where the
        kernels can carry it (they carry ``P`` in the Joseph form and take the model's constant
        ``R``: no factored ``covariance_form``, no ``adaptive_noise``), else none."""
        if self.covariance_form == "joseph" and self.adaptive_noise is None:
            return self.paths
        return NO_FAST_PATHS

    # --- What a corrector tells the kernels (its declared rules aside). ---

    def axis_settings(self, inputs: Inputs) -> tuple[Tensor, Tensor] | None:
        """``(ψ [2, m] or [B, T, 2, m], γ)`` for the per-axis kernel's ``"svsf"`` rule."""
        return None

    def axis_measurements(self, inputs: Inputs) -> axes.AxisMeasurements | None:
        """The corrector's full-state measurements built axis by axis, where a filter can
        (the SVSF's finite-difference velocities); ``None``: split :meth:`measurements`."""
        return None

    def dense_settings(self, dtype: torch.dtype, H: Tensor) -> tuple[float, Tensor] | None:
        """``(γ, ψ [m])`` of a compiled step's corrector, or ``None`` where it cannot run."""
        return 0.0, H.new_zeros(H.shape[0])

    def dense_widths(self, psi: Tensor, dtype: torch.dtype) -> Tensor:
        """A per-step ψ given at call time as the compiled dense steps read it (they run the
        model's constant ``R``), for a run in ``dtype``."""
        return psi

    # --- The routing. ---

    def fast_pass(
        self, state: FilterState, inputs: Inputs
    ) -> tuple[FilterResult, fused_axes.Last] | None:
        """The per-axis kernel, else the compiled dense steps, where they can run the steps of
        ``inputs`` from ``state``."""
        # The per-axis kernel starts from a prior: any state without a corrector's memory or
        # earlier rows is one (a KF's chunks all run there; an SVSF's first chunk).
        fresh = state.steps == 0 or (state.post_innovation is None and state.history is None)
        by_axis = self.axis_pass(inputs) if fresh else None
        if by_axis is not None:
            return by_axis.result, by_axis.last
        dense = self.dense_scan(state, inputs)
        return None if dense is None else (dense, last_step(dense))

    def smoother_pass(
        self, inputs: Inputs, smoothing: str | None = None, lag: int | None = 1
    ) -> tuple[FilterResult, tuple[Tensor, Tensor] | None]:
        """The pass a smoother consumes: the whole record (whatever the caller keeps), or,
        with ``smoothing`` (``"gain"``: RTS, ``"projection"``: SVSS) where the per-axis compiled
        loop runs, the smoothed mean and covariance of ``lag`` (``None``: the fixed interval)
        computed with the filter (lag 1, and other lags where less than the whole record is
        kept: :func:`axes.run_axes`) beside a record that keeps what ``inputs.keep`` keeps."""
        if smoothing is not None:
            by_axis = self.axis_pass(inputs, smoothing, lag)
            if by_axis is not None:  # without the fused smoothing the record is whole
                return by_axis.result, by_axis.smoothed
        return self.run(replace(inputs, keep="all")), None

    # --- The per-axis kernel. ---

    def axis_pass(
        self, inputs: Inputs, smoothing: str | None = None, lag: int | None = 1
    ) -> AxisPass | None:
        """The pass through the per-axis kernel when the problem decouples by axis (a
        :class:`~torchsvs.models.ConstantVelocity` with diagonal ``R``, a prior without cross-axis
        covariance, a position-only or a finite-difference-velocity corrector) and the
        smoothed moments asked for (:func:`axes.run_axes`); else ``None``. Its compiled loop
        writes only what ``inputs.keep`` keeps."""
        model = self.model
        rule = self.supports().axis
        if not AXIS_KERNEL["enabled"] or rule is None:
            return None
        if not isinstance(model, ConstantVelocity):
            return None
        m, n = model.meas_dim, model.state_dim
        dtype = inputs.z.dtype
        R = model.meas_cov().to(dtype)
        cross = ~torch.eye(m, dtype=torch.bool)
        if bool((R[cross] != 0).any()) or bool((inputs.P0[:, _cross_axis(m)] != 0).any()):
            return None
        pos, vel = model.position_index, model.velocity_index
        direct = self.axis_measurements(inputs)
        if direct is not None:
            y, with_velocity = direct, True
            H, R_c = torch.eye(n, dtype=dtype), None
        else:
            measured = self._axis_split(inputs, pos, vel)
            if measured is None:
                return None
            y, with_velocity, H, R_c = measured
        P0 = inputs.P0.expand(inputs.batch, n, n)
        prior = blocks.Sym2(P0[:, pos, pos], P0[:, pos, vel], P0[:, vel, vel])
        interval = inputs.dt if inputs.dt is not None else torch.tensor(model.dt, dtype=dtype)
        settings = self.axis_settings(inputs)
        psi, gamma = settings if settings is not None else (None, None)
        per_axis, out, last, smoothed = axes.run_axes(
            y,
            (inputs.x0[:, pos], inputs.x0[:, vel]),
            prior,
            model.q().to(dtype),
            interval.to(dtype),
            rule,
            psi,
            gamma,
            with_velocity,
            inputs.keep,
            smoothing,
            lag,
        )
        if per_axis is None:  # only the kept moments were written
            none: dict[str, Any] = dict.fromkeys(("transition", "meas_matrix", "meas_cov"))
            return AxisPass(FilterResult(**out._asdict(), **none), last, smoothed)
        F = model.transition(inputs.dt).to(dtype)  # Q is not part of a result
        if R_c is None:  # measured per axis: R (unmasked) from its diagonal blocks
            noise = blocks.Sym2(*torch.broadcast_tensors(*y.noise))
            R_c = blocks.block_diagonal(blocks.full(noise))
        result = FilterResult(
            **out._asdict(),
            transition=as_result_matrix(F),
            meas_matrix=as_result_matrix(H),
            meas_cov=as_result_matrix(R_c),
            axes=per_axis,
        )
        return AxisPass(result, last, smoothed)

    def _axis_split(
        self, inputs: Inputs, pos: list[int], vel: list[int]
    ) -> tuple[axes.AxisMeasurements, bool, Tensor, Tensor] | None:
        """:meth:`measurements` split by axis: positions only, or the full state with ``H = I``
        (and whether velocities are measured, ``H``, ``R``); ``None`` if they couple axes."""
        z, H, R_c = self.measurements(inputs)
        model = self.model
        assert H is not None and isinstance(model, ConstantVelocity)
        m, n = len(pos), model.state_dim
        if H.shape == (n, n) and bool(torch.equal(H, torch.eye(n, dtype=H.dtype))):
            if bool((R_c[..., _cross_axis(m)] != 0).any()):
                return None

            def entry(i: list[int], j: list[int]) -> Tensor:
                return R_c[..., i, j]

            noise = blocks.Sym2(entry(pos, pos), entry(pos, vel), entry(vel, vel))
            return axes.AxisMeasurements(z[..., pos], z[..., vel], noise), True, H, R_c
        if H.shape == (m, n) and bool(torch.equal(H, model.meas_matrix().to(H.dtype))):
            diagonal = R_c.diagonal(dim1=-2, dim2=-1)
            noise = blocks.Sym2(diagonal, torch.zeros_like(diagonal), torch.ones_like(diagonal))
            return (
                axes.AxisMeasurements(z, z.new_tensor(float("nan")).expand_as(z), noise),
                False,
                H,
                R_c,
            )
        return None

    # --- The compiled dense steps. ---

    def dense_ready(self, history: Any) -> bool:
        """Whether the compiled dense steps can stand for this filter's (a linear model of at
        most ``fused_dense.DENSE_MAX`` states and measurements, a corrector with a compiled rule, no
        artificial measurement's rows to carry)."""
        model = self.model
        return (
            self.supports().dense is not None
            and isinstance(model, LinearModel)
            and history is None
            and model.state_dim <= fused_dense.DENSE_MAX
            and model.meas_dim <= fused_dense.DENSE_MAX
        )

    def _dense_constants(self, dtype: torch.dtype) -> DenseConstants | None:
        """The model's matrices and the corrector's settings in ``dtype``, where the compiled
        steps take them."""
        model = self.model
        assert isinstance(model, LinearModel)
        matrices = [
            A.to(dtype).contiguous()
            for A in (model.transition(), model.process_noise(), model.meas_matrix())
        ]
        matrices.append(model.meas_cov().to(dtype).contiguous())
        if not build.usable(*matrices):
            return None
        settings = self.dense_settings(dtype, matrices[2])
        if settings is None:
            return None
        gamma, widths = settings
        tensors = [*self.parameters(), *self.buffers()]
        plain = _plain_settings(model)
        return DenseConstants(
            fused_dense.DenseMatrices(matrices),
            gamma,
            widths.contiguous(),
            tensors,
            plain,
            _fingerprint(tensors, model, plain),
            {},
        )

    def _valid_constants(self, constants: Any, dtype: torch.dtype) -> DenseConstants | None:
        """``constants`` while they still describe the filter and its model, else new ones."""
        model = cast(StateSpaceModel, self._modules["model"])  # (Module.__getattr__: slow)
        if (
            isinstance(constants, DenseConstants)
            and constants.widths.dtype == dtype
            and constants.fingerprint == _fingerprint(constants.tensors, model, constants.settings)
        ):
            # Made without gradients; a parameter they came from may want one now.
            if torch.is_grad_enabled() and any(t.requires_grad for t in constants.tensors):
                return None
            return constants
        return self._dense_constants(dtype)

    def dense_scan(self, state: FilterState, inputs: Inputs) -> FilterResult | None:
        """The steps of ``inputs`` compiled for a linear model with its own interval, without
        gradients (its log-likelihood summed over them); else ``None``."""
        rule = self.supports().dense
        if rule is None or not self.dense_ready(state.history):
            return None
        if inputs.dt is not None or inputs.u is not None:
            return None
        psi = inputs.psi
        if psi is not None:
            if rule != "svsf":
                return None
            psi = self.dense_widths(psi, inputs.z.dtype)
        given = (inputs.z, inputs.x0, inputs.P0, *(() if psi is None else (psi,)))
        if not build.usable(*given):  # (ψ given with a gradient: the differentiable path)
            return None
        B, T = inputs.batch, inputs.steps
        if rule == "kalman" and B > 1 and inputs.P0.shape[0] == 1:
            # A shared prior without missing data: the general path runs one covariance
            # recursion for the whole batch (a broadcast view), less work and memory.
            if not bool(torch.isnan(inputs.z).any()):
                return None
        constants = self._valid_constants(state.constants, inputs.z.dtype)
        if constants is None:
            return None
        x = inputs.x0.expand(B, self.model.state_dim)
        n, m = x.shape[1], inputs.z.shape[-1]
        memory = state.post_innovation
        if rule == "svsf" and memory is None:
            memory = x.new_zeros(B, m)
        out = fused_dense.dense_run(
            rule,
            constants.gamma,
            x.contiguous(),
            (inputs.P0 if inputs.P0.shape[0] == B else inputs.P0.expand(B, n, n)).contiguous(),
            inputs.z.contiguous(),
            x if memory is None else memory.expand(B, m).contiguous(),
            constants.widths if psi is None else psi.to(x.dtype).contiguous(),
            constants.matrices,
            (B, T),
            inputs.keep,
        )
        if out is None:  # an infinity in z, or S not positive definite
            return None
        result = _dense_result(
            DenseOutputs._make(out), rule, constants.matrices, (B, T), inputs.keep
        )
        if result.log_likelihood is None:
            return result
        return result._replace(log_likelihood=result.log_likelihood.sum(1))

    def step_shortcut(
        self, state: Any, z: Tensor, psi: Tensor | None, keep: str
    ) -> tuple[FilterState, FilterResult] | None:
        """One online step compiled (:class:`~torchsvs.kernels.fused_dense.OnlineStep`): a linear
        model without gradients, the model's own interval, the same numbers up to rounding;
        else ``None`` (the one-step scan runs, and names what is wrong). Per call: checks,
        the step's tensors and one library call; ``benchmarks/one_track.md`` times it beside
        filterpy's ``predict`` + ``update``, so every µs here shows."""
        rule = self.supports().dense
        if not isinstance(state, FilterState) or rule is None:
            return None
        if psi is not None:
            psi = self.dense_widths(psi, z.dtype)
        constants = self._online_constants(state, z, psi, rule)
        if constants is None:
            return None
        single = state.single
        B = 1 if single else z.shape[0]
        lead = () if single else (B,)
        key = (keep, lead, threading.get_ident())
        step = constants.steps.get(key)
        if step is None:
            x = state.mean
            step = CompiledStep.of(
                fused_dense.OnlineStep(
                    rule, constants.gamma, constants.matrices, x.shape[1], lead, x.dtype, keep
                )
            )
            constants.steps[key] = step
        return self._online_step(step, state, z, psi, rule, constants, keep)

    def _online_constants(
        self, state: FilterState, z: Tensor, psi: Tensor | None, rule: str
    ) -> DenseConstants | None:
        """The constants of a compiled online step from ``state`` over ``z``, or ``None``
        where it cannot run (see :meth:`step_shortcut`)."""
        x, single, known = state.mean, state.single, state.constants
        if torch.is_grad_enabled() and psi is not None and psi.requires_grad:
            return None
        if known is None:
            if not self.dense_ready(state.history) or not build.usable(z, x):
                return None  # (usable: CPU float32/64, no gradient, compiler available)
            m = self.model.meas_dim
        else:
            # A state an earlier compiled step made: its x is a CPU float tensor and the
            # library loaded; what may have changed is z, the mode, and whether a gradient is
            # asked for (of z or of a state a caller edited, here; of a parameter, in
            # _valid_constants).
            if not (AXIS_KERNEL["fused"] and z.is_cpu):
                return None
            if torch.is_grad_enabled() and (
                z.requires_grad or x.requires_grad or state.cov.requires_grad
            ):
                return None
            m = known.matrices.meas_dim
        if z.ndim != (1 if single else 2) or z.shape[-1] != m or z.dtype != x.dtype:
            return None
        B = 1 if single else z.shape[0]
        if x.shape[0] != B or B == 0:
            return None
        if psi is not None and (rule != "svsf" or psi.shape != z.shape):
            return None  # (the scan names what is wrong)
        return self._valid_constants(known, x.dtype)

    def _online_step(
        self,
        step: CompiledStep,
        state: FilterState,
        z: Tensor,
        psi: Tensor | None,
        rule: str,
        constants: DenseConstants,
        keep: str,
    ) -> tuple[FilterState, FilterResult] | None:
        """The compiled ``step`` from ``state`` over ``z``: the state after it (with the
        batch axis) and its result (without it for one track), or ``None`` where the library
        declined (an infinity in ``z``, ``S`` not positive definite)."""
        x, single = state.mean, state.single
        B, m = x.shape[0], constants.matrices.meas_dim
        P, memory = state.cov, state.post_innovation
        if P.shape[0] != B:  # a prior shared by the batch, before the first step
            P = P.expand(B, *P.shape[1:])
        if memory is None:  # the SVSF's memory before the first step (the KF reads none)
            memory = x if rule == "kalman" else x.new_zeros(B, m)
        elif memory.shape[0] != B:  # one memory shared by the batch
            memory = memory.expand(B, m).contiguous()
        widths = constants.widths if psi is None else psi.to(x.dtype).contiguous()
        total = state.log_likelihood  # (the library reads it as x's dtype, contiguous)
        total = None if total is None else total.to(x.dtype).contiguous()
        done = step.call(x.contiguous(), P.contiguous(), z.contiguous(), memory, widths, total)
        if done is None:
            return None
        kept, after = done
        out = DenseOutputs._make(step.pick([*kept, None]))
        mean, cov, e_post = out.mean, out.cov, out.post_innovation
        if single:  # the state keeps the batch axis; the step's result of one track drops it
            mean, cov = mean[None], cov[None]
            e_post = None if e_post is None else e_post[None]
        after_state = FilterState(
            mean=mean,
            cov=cov,
            post_innovation=e_post,
            log_likelihood=after,
            steps=state.steps + 1,
            single=single,
            constants=constants,
        )
        lead = () if single else (B,)
        if keep == "all":
            return after_state, _dense_result(out, rule, constants.matrices, lead, keep)
        nothing: Any = None  # the fields a kept result leaves out (FilterResult's doc)
        result = FilterResult(
            mean=out.mean,
            cov=out.cov if keep == "moments" else nothing,
            pred_mean=nothing,
            pred_cov=nothing,
            innovation=nothing,
            mask=nothing,
            transition=nothing,
            meas_matrix=nothing,
            meas_cov=nothing,
            gain=nothing,
            log_likelihood=out.log_likelihood if rule == "kalman" else None,
        )
        return after_state, result


def _cross_axis(m: int) -> Tensor:
    """``[2m, 2m]`` True where a state covariance couples different axes (layout x, vx, y, ...)."""
    axis = torch.arange(2 * m) // 2
    return axis[:, None] != axis[None, :]
