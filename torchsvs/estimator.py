"""The call contract shared by every estimator: input checks, the batch axis, the result.

``est(z, x0, P0, *, u=None, dt=None, psi=None, generator=None)`` checks its inputs here once,
adds the batch axis to a single track, runs the estimator on ``[B, T, ...]`` tensors and drops
the batch axis again from the result. Bad input raises ``ValueError``/``TypeError`` naming the
argument, its shape and what was expected.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from numbers import Real
from typing import Any, Generic, TypeVar

import torch
from torch import Tensor, nn

from torchsvs.accuracy import PROBE_STEP
from torchsvs.kernels.compiled import outside_dynamo
from torchsvs.linalg import holds_inf
from torchsvs.models.base import StateSpaceModel
from torchsvs.types import Inputs


def _shape(x: Any) -> str:
    return str(tuple(x.shape)) if isinstance(x, Tensor) else type(x).__name__


def _as_float_tensor(value: Any, name: str, dtype: torch.dtype) -> Tensor:
    if isinstance(value, Tensor):
        if not (value.is_floating_point() or value.dtype in (torch.int32, torch.int64)):
            raise TypeError(f"{name}: expected a real tensor, got dtype {value.dtype}")
        return value.to(dtype)
    try:
        return torch.as_tensor(value, dtype=dtype)
    except (TypeError, ValueError) as err:
        raise TypeError(f"{name}: expected a tensor, got {type(value).__name__}") from err


def _check_dtype(value: Any, name: str, dtype: torch.dtype) -> None:
    """Refuses a floating tensor of another dtype than ``z``'s: converting it silently would
    round a float64 prior (or lose nothing, and hide which precision ran). Numbers, lists and
    arrays are converted; integer tensors too. Checked after the shape and values, so those
    errors come first."""
    if isinstance(value, Tensor) and value.is_floating_point() and value.dtype != dtype:
        raise TypeError(
            f"{name}: dtype {value.dtype} differs from z's dtype {dtype}; the computation runs "
            f"in z's dtype: pass {name}.to({dtype}) (or z in {value.dtype})"
        )


def prepare_inputs(
    model: StateSpaceModel,
    z: Any,
    x0: Any,
    P0: Any,
    *,
    u: Any = None,
    dt: Any = None,
    psi: Any = None,
    generator: torch.Generator | None = None,
    state_prior: bool = False,
    keep: str = "all",
) -> Inputs:
    """Checks every argument of an estimator call against ``model`` and adds the batch axis.

    ``state_prior``: ``x0 [b, n]``, ``P0 [b, n, n]`` are an estimator's own state (``b`` the
    state's tracks, or 1 for a prior shared by the batch), checked when it was made: only their
    batch is checked against ``z``'s."""
    m = model.meas_dim
    if not isinstance(z, Tensor):
        raise TypeError(f"z: expected a tensor [B, T, {m}] or [T, {m}], got {type(z).__name__}")
    if z.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"z: expected float32 or float64, got {z.dtype}")
    if z.ndim not in (2, 3) or z.shape[-1] != m or z.shape[-2] < 1:
        raise ValueError(f"z: expected shape [B, T, {m}] or [T, {m}] with T >= 1, got {_shape(z)}")
    if holds_inf(z):
        raise ValueError("z: contains inf; mark a missing measurement with NaN instead")
    dtype, single = z.dtype, z.ndim == 2
    zb = z.unsqueeze(0) if single else z
    B, T = zb.shape[:2]
    if B == 0:
        raise ValueError(f"z: expected at least one track, got shape {_shape(z)}")

    if state_prior:
        if x0.shape[0] not in (1, B):
            raise ValueError(
                f"z: expected {x0.shape[0]} tracks, as the state has, got shape {_shape(z)}"
            )
        x0, P0 = x0.to(dtype).expand(B, -1), P0.to(dtype)
    else:
        given = (x0, P0)
        x0, P0 = _check_prior(model, x0, P0, B, single, dtype)
        _check_dtype(given[0], "x0", dtype)
        _check_dtype(given[1], "P0", dtype)

    u_t = None
    if u is not None:
        p = model.input_dim
        if p == 0:
            raise ValueError(f"u: {type(model).__name__} takes no control input; expected None")
        u_t = _as_float_tensor(u, "u", dtype)
        if single:
            u_t = u_t.unsqueeze(0)
        if u_t.shape != (B, T, p):
            want = f"[T, {p}]" if single else f"[{B}, {T}, {p}]"
            raise ValueError(f"u: expected shape {want}, got {_shape(u)}")
        if not bool(torch.isfinite(u_t).all()):
            raise ValueError("u: contains NaN or inf")
        _check_dtype(u, "u", dtype)
    dt_t = _check_dt(model, dt, B, T, single, dtype)
    _check_dtype(dt, "dt", dtype)
    psi_t = None
    if psi is not None:
        psi_t = _as_float_tensor(psi, "psi", dtype)
        if single:
            psi_t = psi_t.unsqueeze(0)
        if psi_t.ndim != 3 or psi_t.shape[:2] != (B, T):
            want = "[T, m]" if single else f"[{B}, {T}, m]"
            raise ValueError(
                f"psi: expected a per-step override of shape {want}, got {_shape(psi)}"
            )
        if not bool(torch.isfinite(psi_t).all()) or bool((psi_t <= 0).any()):
            raise ValueError("psi: expected finite boundary layer widths > 0")
        _check_dtype(psi, "psi", dtype)
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"generator: expected a torch.Generator, got {type(generator).__name__}")
    check_keep(keep)
    return Inputs(zb, x0, P0, dt_t, u_t, psi_t, generator, single, keep)


def check_keep(keep: Any) -> None:
    if not isinstance(keep, str) or keep not in KEEP:
        raise ValueError(f"keep: expected one of {', '.join(map(repr, KEEP))}, got {keep!r}")


def _check_prior(
    model: StateSpaceModel, x0: Any, P0: Any, B: int, single: bool, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """``x0 [B, n]`` and ``P0 [B|1, n, n]``, checked."""
    n = model.state_dim
    x0 = _as_float_tensor(x0, "x0", dtype)
    if x0.shape == (n,):
        x0 = x0.expand(B, n)
    elif x0.shape != (B, n) or single:
        want = f"[n] = [{n}]" if single else f"[B, n] = [{B}, {n}] or [n] = [{n}]"
        raise ValueError(f"x0: expected shape {want}, got {_shape(x0)}")
    if not bool(torch.isfinite(x0).all()):
        raise ValueError("x0: contains NaN or inf")

    P0 = _as_float_tensor(P0, "P0", dtype)
    if P0.shape == (n, n):
        # Kept with a batch axis of 1: while nothing track-specific enters (a KF without missing
        # data), the covariance recursion then runs once for the whole batch.
        P0 = P0.unsqueeze(0)
    elif P0.shape != (B, n, n) or single:
        shared = f"[n, n] = [{n}, {n}]"
        want = shared if single else f"[B, n, n] = [{B}, {n}, {n}] or {shared}"
        raise ValueError(f"P0: expected shape {want}, got {_shape(P0)}")
    if not bool(torch.isfinite(P0).all()):
        raise ValueError("P0: contains NaN or inf")
    scale = P0.abs().amax().clamp_min(torch.finfo(dtype).tiny)
    if bool(((P0 - P0.mT).abs() > 1e3 * torch.finfo(dtype).eps * scale).any()):
        raise ValueError(f"P0: expected a symmetric matrix, shape {_shape(P0)}")
    if bool((torch.linalg.cholesky_ex(P0).info > 0).any()):
        raise ValueError(f"P0: expected a positive definite matrix, shape {_shape(P0)}")

    return x0, P0


def prepare_prior(model: StateSpaceModel, x0: Any, P0: Any) -> tuple[Tensor, Tensor, bool]:
    """A prior on its own (``est.init``): ``x0 [B, n]`` or one track's ``[n]``, in ``x0``'s
    dtype (float32 or float64); returns it batched and whether it was one track."""
    if not isinstance(x0, Tensor):
        raise TypeError(f"x0: expected a tensor [B, n] or [n], got {type(x0).__name__}")
    if x0.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"x0: expected float32 or float64, got {x0.dtype}")
    n = model.state_dim
    if x0.ndim not in (1, 2) or x0.shape[-1] != n:
        raise ValueError(f"x0: expected shape [B, n] or [n] = [{n}], got {_shape(x0)}")
    single = x0.ndim == 1
    B = 1 if single else x0.shape[0]
    if B == 0:
        raise ValueError(f"x0: expected at least one track, got shape {_shape(x0)}")
    x0b, P0b = _check_prior(model, x0, P0, B, single, x0.dtype)
    if isinstance(P0, Tensor) and P0.is_floating_point() and P0.dtype != x0.dtype:
        raise TypeError(
            f"P0: dtype {P0.dtype} differs from x0's dtype {x0.dtype} (the state's dtype); "
            f"pass P0.to({x0.dtype})"
        )
    if single:
        x0b, P0b = x0b.reshape(1, n), P0b.reshape(1, n, n)
    return x0b, P0b, single


def _check_dt(
    model: StateSpaceModel, dt: Any, B: int, T: int, single: bool, dtype: torch.dtype
) -> Tensor | None:
    if dt is None:
        return None
    if not model.uses_dt:
        raise ValueError(f"dt: {type(model).__name__} has fixed matrices; expected dt=None")
    if isinstance(dt, Real) and not isinstance(dt, bool):
        dt = torch.tensor(float(dt), dtype=dtype)
    dt_t = _as_float_tensor(dt, "dt", dtype)
    if single and dt_t.ndim == 1:
        dt_t = dt_t.unsqueeze(0)
    if dt_t.ndim != 0 and dt_t.shape != (B, T):
        want = "a scalar or [T]" if single else f"a scalar or [{B}, {T}]"
        raise ValueError(f"dt: expected {want}, got {_shape(dt)}")
    if not bool(torch.isfinite(dt_t).all()) or bool((dt_t <= 0).any()):
        raise ValueError("dt: expected finite intervals > 0")
    return dt_t


#: Problems whose per-step covariances hold fewer elements (``B·n²``) run on one intra-op
#: thread: the step loop is a long chain of small operations, and a second thread costs more
#: in synchronisation than it brings (measured by ``benchmarks/threads.py``, ``make bench``).
SMALL_PROBLEM = 1 << 12


@contextmanager
def threads_for(batch: int, n: int) -> Iterator[None]:
    """Runs the block on one intra-op thread when ``B·n² <`` :data:`SMALL_PROBLEM` (and with
    the caller's setting otherwise); the setting is restored afterwards. It is process-wide
    while the block runs."""
    before = torch.get_num_threads()
    if before == 1 or batch * n * n >= SMALL_PROBLEM:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


#: Result fields without a time axis: the run's totals and its final particles.
RUN_FIELDS = ("log_likelihood", "particles", "log_weights")

#: What an estimator's result keeps of each step (``keep`` of every call): ``"all"`` (the
#: whole result: predictions, innovations, gains, ``S``, ..., what smoothers and losses read),
#: ``"moments"`` (``mean`` and ``cov``) or ``"mean"`` (no covariance history). The fields not
#: kept are ``None``; the run's totals (:data:`RUN_FIELDS`) stay.
KEEP = ("all", "moments", "mean")


def trim(result: Any, keep: str) -> Any:
    """``result`` with the per-step fields that ``keep`` (:data:`KEEP`) leaves out set to
    ``None`` (a smoother's filter pass trimmed the same way)."""
    if keep == "all":
        return result
    kept = ("mean",) if keep == "mean" else ("mean", "cov")
    fields = []
    for name, value in zip(result._fields, result, strict=True):
        if name == "filtered":
            value = trim(value, keep)
        elif name not in kept and name not in RUN_FIELDS:
            value = None
        fields.append(value)
    return type(result)(*fields)


def at_step(result: Any, t: int, time_axis: int = 1) -> Any:
    """Step ``t`` of every per-step tensor of a result NamedTuple (the run's totals, such as the
    log-likelihood, as they are; internals dropped)."""
    fields = []
    for name, value in zip(result._fields, result, strict=True):
        if name == "axes":
            value = None
        elif isinstance(value, Tensor) and name not in RUN_FIELDS:
            value = value.select(time_axis, min(t, value.shape[time_axis] - 1))
        elif _results(value):  # one result per mode (an IMM's)
            value = tuple(at_step(v, t, time_axis) for v in value)
        fields.append(value)
    return type(result)(*fields)


def _results(value: Any) -> bool:
    """Whether ``value`` is a plain tuple of result NamedTuples (an IMM's per-mode results)."""
    return (
        isinstance(value, tuple)
        and not hasattr(value, "_fields")
        and all(hasattr(v, "_fields") for v in value)
    )


def drop_batch(result: Any) -> Any:
    """Removes the leading batch axis (of size 1) from every tensor of a result NamedTuple."""
    fields = []
    for name, value in zip(result._fields, result, strict=True):
        if name == "axes":
            value = None  # the per-axis internals stay batched: not part of a single track's result
        elif isinstance(value, Tensor):
            value = value.squeeze(0)
        elif _results(value):
            value = tuple(drop_batch(v) for v in value)
        elif isinstance(value, tuple):
            value = drop_batch(value)
        fields.append(value)
    return type(result)(*fields)


def split_batch(result: Any, first: int) -> tuple[Any, Any]:
    """A result of a run over two batches side by side, ``[B1 + B2, ...]``, as the results of
    the first ``first`` rows and of the rest (every tensor of the NamedTuple, and of the
    NamedTuples and tuples inside it, cut along its leading batch axis)."""
    if isinstance(result, Tensor) and result.ndim:
        return result[:first], result[first:]
    if isinstance(result, tuple):
        pairs = [split_batch(value, first) for value in result]
        make: Any = getattr(type(result), "_make", type(result))  # a NamedTuple or a tuple
        return make(p[0] for p in pairs), make(p[1] for p in pairs)
    return result, result


#: What an estimator returns: a FilterResult, SmootherResult or ParticleResult.
Result = TypeVar("Result")


class Estimator(nn.Module, Generic[Result]):
    """Base of every filter and smoother: ``forward`` checks inputs, ``run`` does the work.

    Subclasses implement :meth:`run` on checked, batched :class:`Inputs`, returning their
    ``Result`` type. Nothing about a run is stored on the module.
    """

    model: StateSpaceModel

    #: Whether SURE's probed run (:func:`~torchsvs.fitting.losses.stein_risk`,
    #: :func:`~torchsvs.accuracy.risk_terms`) goes in one batch with the plain run: for
    #: estimators deterministic in ``z`` whose run costs its steps more than its rows (the
    #: IMM's Python step loop: twice the rows cost 1.3-1.5x, two runs 2x).
    paired_probes = False
    #: The truth-free error estimate's finite-difference step in noise standard deviations
    #: (:func:`~torchsvs.accuracy.risk_terms`).
    probe_step = PROBE_STEP

    @outside_dynamo  # a user's torch.compile: the time loop stays outside Dynamo
    def forward(
        self,
        z: Tensor,
        x0: Tensor,
        P0: Tensor,
        *,
        u: Tensor | None = None,
        dt: float | Tensor | None = None,
        psi: Tensor | None = None,
        generator: torch.Generator | None = None,
        keep: str = "all",
    ) -> Result:
        """Estimates the states of every track.

        Args:
            z: measurements ``[B, T, m]`` (or ``[T, m]``); NaN marks a missing component.
            x0: prior mean one step before ``z[:, 0]``, ``[B, n]`` or ``[n]``.
            P0: prior covariance, ``[B, n, n]`` or ``[n, n]``, symmetric positive definite.
            u: control inputs ``[B, T, p]``; the linear models take none.
            dt: per-step intervals, a scalar or ``[B, T]``, for models whose F and Q depend on it.
            psi: per-step boundary layer override ``[B, T, m]`` for SVSF-based estimators.
            generator: source of randomness for stochastic estimators.
            keep: what the result keeps of each step: ``"all"``, ``"moments"`` (means and
                covariances) or ``"mean"`` (:data:`KEEP`); less to keep is less memory and, in
                the compiled loops, less to write.

        Returns:
            A :class:`~torchsvs.types.FilterResult`, :class:`~torchsvs.types.SmootherResult` or
            :class:`~torchsvs.filters.particle.ParticleResult`.

        The computation runs in ``z``'s dtype (float32 or float64). ``x0``, ``P0``, ``u``,
        ``dt`` and ``psi`` given as floating tensors must have that dtype (``TypeError`` naming
        the argument and both dtypes otherwise); numbers, lists and NumPy arrays are converted
        to it. The module's parameters are cast to it, so a float64 module given float32 ``z``
        computes in float32 (pass float64 ``z`` for float64 results). Gradients still reach
        the parameters.
        """
        self.check_psi(psi)
        inputs = prepare_inputs(
            self.model, z, x0, P0, u=u, dt=dt, psi=psi, generator=generator, keep=keep
        )
        with threads_for(inputs.batch, self.model.state_dim):
            result = trim(self.run(inputs), keep)
        return drop_batch(result) if inputs.single else result

    def run(self, inputs: Inputs) -> Result:
        raise NotImplementedError

    def takes_psi(self) -> bool:
        """Whether a per-step boundary layer override ``psi`` applies to this estimator."""
        return False

    def check_psi(self, psi: Any) -> None:
        """Refuses a ``psi`` this estimator would ignore."""
        if psi is not None and not self.takes_psi():
            raise ValueError(
                f"psi: {type(self).__name__} has no boundary layer to override; a per-step psi "
                "applies to the SVSF and the smoothers over it"
            )


class SteppedEstimator(Estimator[Result]):
    """An estimator that also runs one step or one chunk of steps at a time from a state it
    returns (``init``, ``step``, ``scan``; nothing kept on the module): the filters. ``forward``
    is ``init`` and one ``scan``. Subclasses give :meth:`init`, :meth:`_scan` and
    :meth:`state_prior`."""

    #: the carry type of :meth:`init`, :meth:`step` and :meth:`scan`
    state_type: type[Any] = tuple

    @outside_dynamo
    def scan(
        self,
        state: Any,
        z: Tensor,
        *,
        u: Tensor | None = None,
        dt: float | Tensor | None = None,
        psi: Tensor | None = None,
        generator: torch.Generator | None = None,
        keep: str = "all",
    ) -> tuple[Any, Result]:
        """Runs the steps ``z [B, T, m]`` (``[T, m]`` for a state of one track) from ``state``:
        the state after the last of them and their result, as :meth:`forward` gives it (a
        recording run in chunks, the state carried between them, gives the same numbers).
        ``u``, ``dt``, ``psi``, ``generator``, ``keep`` as for :meth:`forward` (a stochastic
        estimator equals its whole run when one generator is passed to ``init`` and every
        call; the state is whole whatever ``keep`` drops)."""
        if not isinstance(state, self.state_type):
            raise TypeError(
                f"state: expected a {self.state_type.__name__} (est.init), "
                f"got {type(state).__name__}"
            )
        self.check_psi(psi)
        x0, P0 = self.state_prior(state)
        inputs = prepare_inputs(
            self.model,
            z,
            x0,
            P0,
            u=u,
            dt=dt,
            psi=psi,
            generator=generator,
            state_prior=True,
            keep=keep,
        )
        if state.single and not inputs.single and state.steps == 0:
            state = self.share(state, inputs)
        elif inputs.single != state.single:
            want = "[T, m] (one track)" if state.single else "[B, T, m]"
            raise ValueError(f"z: expected shape {want} for this state, got {tuple(z.shape)}")
        with threads_for(inputs.batch, self.model.state_dim):
            state, result = self._scan(state, inputs)
        result = trim(result, keep)
        return state, drop_batch(result) if inputs.single else result

    @outside_dynamo
    def step(
        self,
        state: Any,
        z: Tensor,
        *,
        u: Tensor | None = None,
        dt: float | Tensor | None = None,
        psi: Tensor | None = None,
        generator: torch.Generator | None = None,
        keep: str = "all",
    ) -> tuple[Any, Result]:
        """One step for ``z [B, m]`` (``[m]`` for one track; NaN: missing): the new state and the
        step's result (the result's fields without the time axis). ``dt`` a scalar or ``[B]``,
        ``u [B, p]``, ``psi [B, m']``; ``keep`` as for :meth:`forward` (the state is whole)."""
        if not isinstance(z, Tensor):
            raise TypeError(f"z: expected a tensor [B, m] or [m], got {type(z).__name__}")
        if u is None and dt is None and keep in KEEP:
            shortcut = self.step_shortcut(state, z, psi, keep)
            if shortcut is not None:
                return shortcut

        def one_step(x: Any) -> Any:
            return x.unsqueeze(-2) if isinstance(x, Tensor) and x.ndim >= 1 else x

        if isinstance(dt, Tensor) and dt.ndim == 1 and z.ndim == 2:
            dt = dt.unsqueeze(-1)
        state, result = self.scan(
            state,
            one_step(z),
            u=one_step(u),
            dt=dt,
            psi=one_step(psi),
            generator=generator,
            keep=keep,
        )
        return state, at_step(result, 0, time_axis=0 if state.single else 1)

    def step_shortcut(
        self, state: Any, z: Tensor, psi: Tensor | None, keep: str
    ) -> tuple[Any, Result] | None:
        """A faster way to the same :meth:`step` (the model's own interval, no input; its result
        keeping what ``keep`` keeps), or ``None``: then, and for every error message, the step
        runs as a one-step :meth:`scan`."""
        return None

    def state_prior(self, state: Any) -> tuple[Tensor, Tensor]:
        """``x0 [b, n]``, ``P0 [b, n, n]`` standing for ``state`` in the :class:`Inputs` of a
        :meth:`scan` (their batch is what the call checks)."""
        raise NotImplementedError

    def share(self, state: Any, inputs: Inputs) -> Any:
        """The state of one track before its first step, shared by the batch of ``inputs``."""
        raise ValueError(
            f"z: expected shape [T, m] (one track) for this state, got {tuple(inputs.z.shape)}"
        )

    def _scan(self, state: Any, inputs: Inputs) -> tuple[Any, Result]:
        raise NotImplementedError
