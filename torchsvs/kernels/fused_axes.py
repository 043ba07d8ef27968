"""The per-axis kernel's time loops, compiled (``cpp/axis_*.h``, ``cpp/adjoints.h``; built by
:mod:`torchsvs.kernels.build`).

A step of the per-axis recursions (:mod:`torchsvs.kernels.axes`) is a few dozen flops per
track and axis; as tensor operations it costs a few dozen dispatches of about a microsecond
each, so on a dozen long tracks (recorded flights) the loop, not the arithmetic, is the cost.
The compiled loops step blocks of lanes together, take ``[B, T, m]`` views (strides, no
copies) in and write the results in the general layout (what a
:class:`~torchsvs.types.FilterResult` holds) directly, on ``torch.get_num_threads()`` threads
for large batches, into buffers advised as huge pages (:func:`~torchsvs.kernels.build.fresh`).

The forward loop and the smoother's general backward recursion have compiled reverse modes too
(:func:`adjoint`, :func:`backward_adjoint`, used by :class:`torchsvs.kernels.axes._CompiledAxes`
and :class:`torchsvs.kernels.axes_smoother._CompiledSmoother`), so training runs them at near
inference speed and keeps no graph of small tensors (the RTS fixed interval, whose own loop
:func:`rts_interval` has no reverse mode, trains through the general recursion). Compiled and
tensor loops give the same numbers and gradients up to rounding (tested to 1e-10 in float64).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from torch import Tensor

from torchsvs.kernels import build
from torchsvs.kernels.build import fresh, pointers


class _Arrays:
    """Pointers and ``[B, T, m]`` element strides of tensors, kept alive for a call."""

    def __init__(self, tensors: Sequence[Tensor], shape: tuple[int, int, int]) -> None:
        views = [self.view(x, shape) for x in tensors]
        self.tensors = views
        self.pointers = pointers(views)
        self.strides = build.strides(views)

    @staticmethod
    def view(x: Tensor, shape: tuple[int, int, int]) -> Tensor:
        """``x`` as ``[B, T, m]``; broadcast dimensions get stride 0."""
        if x.ndim == 2:  # per track [B, m]
            x = x.unsqueeze(1)
        elif x.ndim < 2:  # constant, or one value per axis [m]
            x = x.reshape(1, 1, -1)
        return x.expand(shape)


#: Most axes the compiled forward loop steps (``kLanes`` in ``cpp/axis_step.h``); more take the
#: tensor loops.
MAX_AXES = 64
#: The compiled loops' codes of the per-axis rules (``Rule`` in ``cpp/axis_step.h``); the
#: variable boundary layer's ``"gain"`` inflation has tensor loops only.
RULES = {"kalman": 0, "svsf": 1, "vbl-innovation": 2}


def compiles(rule: str, axes: int, dtype: torch.dtype) -> bool:
    """Whether the compiled loops run ``rule`` on tracks of ``axes`` axes in ``dtype``: a rule
    that couples a track's axes (the variable boundary layer's one λ per track) needs a track
    whole in one vector of lanes (``lanes_per_vector`` in ``cpp/lanes.h``): at most
    :func:`~torchsvs.kernels.build.lane_width` axes (float64: 8 with AVX-512, 4 with AVX, 2
    with SSE2 or NEON)."""
    if rule not in RULES:
        return False
    if rule.startswith("vbl-"):
        return axes <= build.lane_width(dtype)
    return axes <= MAX_AXES


class Last(NamedTuple):
    """The state after a pass's last step (what its next chunk starts from)."""

    mean: Tensor  #: [B, n]
    cov: Tensor  #: [B, n, n]
    post_innovation: Tensor | None  #: [B, m_z] (SVSF), else None

    @staticmethod
    def empty(B: int, n: int, mz: int | None, dtype: torch.dtype) -> Last:
        """Buffers for a loop to write (``mz`` None: no a-posteriori innovation)."""
        post = None if mz is None else torch.empty(B, mz, dtype=dtype)
        return Last(torch.empty(B, n, dtype=dtype), torch.empty(B, n, n, dtype=dtype), post)


#: The per-step outputs of :func:`forward` each ``keep`` writes, by index (mean, cov, predicted
#: mean and cov, innovation, gain, S, a-posteriori innovation).
KEPT = {"all": range(8), "moments": (0, 1), "mean": (0,)}
#: The compiled loops' codes of the smoother's gain (``"gain"``: RTS, ``"projection"``: SVSS).
_SMOOTHING = {None: 0, "gain": 1, "projection": 2}


def forward(
    rule: str,
    gamma: float,
    given: Sequence[Tensor],
    prior: Sequence[Tensor],
    shape: tuple[int, int, int],
    velocity: bool,
    keep: str = "all",
    smoothing: str | None = None,
) -> tuple[tuple[Tensor | None, ...], Last, tuple[Tensor, Tensor] | None]:
    """The loop of :func:`torchsvs.kernels.axes._forward_step` over all steps, writing the
    general layout (state ``p1, v1, p2, ...``): ``given`` the 11 per-step quantities ``T, Qa,
    Qb, Qc, y_p, y_v`` (NaN: missing), ``r_pp, r_pv, r_vv`` (unmasked), ``w_p, w_v``
    (``[B, T, m]``-broadcastable), ``prior`` ``(p, v, a, b, c)`` ``[B, m]``; ``velocity``: the
    corrector measures velocities (``m_z = 2m``), else positions (``m_z = m``). Returns the mean
    ``[B, T, 2m]``, covariance, predicted mean and covariance, innovation ``[B, T, m_z]``, gain
    ``[B, T, 2m, m_z]``, ``S``, the a-posteriori innovation (SVSF, else ``None``), the
    log-likelihood ``[B]`` (Kalman, else ``None``) and the observed mask ``[B, T, m_z]`` (the
    per-step outputs that ``keep`` (:data:`torchsvs.estimator.KEEP`, :data:`KEPT`) leaves
    out are ``None``, never written), the state after the last step,
    and with ``smoothing`` (``"gain"``: the RTS, ``"projection"``: the SVSS) the one-step-lag
    smoothed mean ``[B, T, 2m]`` and covariance ``[B, T, 2m, 2m]``, computed in the same loop
    (what :func:`backward` with lag 1 gives from the whole record), else ``None``."""
    B, T, m = shape
    n, mz = 2 * m, 2 * m if velocity else m
    dtype = prior[0].dtype
    # The a-posteriori innovation of the SVSF family, the log-likelihood of the Kalman rules.
    post, likelihood = rule != "kalman", rule != "svsf"
    kept = KEPT[keep]
    shapes = ((n,), (n, n), (n,), (n, n), (mz,), (n, mz), (mz, mz), (mz,))
    per_step: list[Tensor | None] = [
        fresh((B, T, *tail), dtype) if i in kept and (post or i < 7) else None
        for i, tail in enumerate(shapes)
    ]
    loglik = torch.empty(B, dtype=dtype) if likelihood else None
    mask = fresh((B, T, mz), torch.bool) if keep == "all" else None
    last = Last.empty(B, n, mz if post else None, dtype)
    smoothed = None
    if smoothing is not None:
        smoothed = fresh((B, T, n), dtype), fresh((B, T, n, n), dtype)
    outputs = (*per_step, loglik, mask, *last, *(smoothed or (None, None)))
    mode = _SMOOTHING[smoothing]
    _forward_loop("forward", rule, gamma, given, prior, shape, velocity, pointers(outputs), mode)
    return (*per_step, loglik, mask), last, smoothed


def filter_pass(
    rule: str,
    gamma: float,
    given: Sequence[Tensor],
    prior: Sequence[Tensor],
    shape: tuple[int, int, int],
    velocity: bool,
    keep: str,
    smoothing: str | None,
    lag: int | None,
) -> tuple[tuple[Tensor | None, ...], Last, tuple[Tensor, Tensor] | None]:
    """The filter's compiled pass with the smoothing asked for: :func:`forward` (none, or lag
    1 as it steps) or :func:`filter_smoother` (another lag)."""
    settings = (rule, gamma, given, prior, shape, velocity, keep)
    if smoothing is not None and lag != 1:
        return filter_smoother(*settings, smoothing, lag)
    return forward(*settings, smoothing)


def filter_smoother(
    rule: str,
    gamma: float,
    given: Sequence[Tensor],
    prior: Sequence[Tensor],
    shape: tuple[int, int, int],
    velocity: bool,
    keep: str,
    smoothing: str,
    lag: int | None,
) -> tuple[tuple[Tensor | None, ...], Last, tuple[Tensor, Tensor]]:
    """:func:`forward` (same arguments, ``keep`` ``"moments"`` or ``"mean"``) and
    :func:`backward` over its record in one compiled pass: the filter's record stays in the
    loop's own buffers, a vector of lanes at a time, and is never written. Returns what
    :func:`forward` does (the fields ``keep`` leaves out ``None``; no mask), the state after
    the last step and the smoothed mean ``[B, T, 2m]`` and covariance
    ``[B, T, 2m, 2m]``."""
    if keep not in ("moments", "mean"):
        raise ValueError(f"keep: expected 'moments' or 'mean', got {keep!r}")
    B, T, m = shape
    n, mz = 2 * m, 2 * m if velocity else m
    dtype = prior[0].dtype
    mean = fresh((B, T, n), dtype)
    cov = fresh((B, T, n, n), dtype) if keep == "moments" else None
    last = Last.empty(B, n, mz if rule != "kalman" else None, dtype)
    smoothed = fresh((B, T, n), dtype), fresh((B, T, n, n), dtype)
    per_step = (mean, cov, *(None,) * 6)
    loglik = torch.empty(B, dtype=dtype) if rule != "svsf" else None
    outputs = (*per_step, loglik, None, *last, *smoothed)
    sweeps, projection = _backward_settings(shape, lag, smoothing == "projection")
    _forward_loop(
        "filter_smoother", rule, gamma, given, prior, shape, velocity, pointers(outputs),
        sweeps, projection,
    )  # fmt: skip
    return (*per_step, loglik, None), last, smoothed


def _forward_loop(
    name: str,
    rule: str,
    gamma: float,
    given: Sequence[Tensor],
    prior: Sequence[Tensor],
    shape: tuple[int, int, int],
    velocity: bool,
    *buffers: object,
) -> None:
    """Calls the compiled function ``name`` (the forward loop or its adjoint) with the forward
    loop's arguments, then ``buffers``."""
    B, T, m = shape
    inputs, start = _Arrays(given, shape), _Arrays(prior, (B, 1, m))
    build.function(name, prior[0].dtype)(
        *shape,
        RULES[rule],
        int(velocity),
        float(gamma),
        build.threads(B, T),
        inputs.pointers,
        inputs.strides,
        start.pointers,
        start.strides,
        *buffers,
    )


def adjoint(
    rule: str,
    gamma: float,
    given: Sequence[Tensor],
    prior: Sequence[Tensor],
    shape: tuple[int, int, int],
    velocity: bool,
    grads: Sequence[Tensor | None],
    wanted: Sequence[bool],
    smoothing: str | None = None,
    lag: int | None = 1,
) -> tuple[list[Tensor | None], list[Tensor], Tensor]:
    """The reverse mode of :func:`forward` (same arguments), or with a ``lag`` other than 1
    of :func:`filter_smoother`: ``grads`` the gradients of the outputs (``None``: zero): the
    eight per-step ones and the log-likelihood, the state after the last step (mean, cov,
    a-posteriori innovation) and the smoothed mean and cov (with ``smoothing``), 14 in all;
    ``wanted`` which of the 11 ``given`` need one. Returns the
    ``given`` gradients ``[B, T, m]``, or ``[B, 1, m]`` summed over the steps for an input
    constant in time (``None`` where not wanted; the caller sums them to each input's shape),
    the prior's ``[B, m]`` and ``γ``'s per lane ``[B, m]``."""
    B, T, m = shape
    dtype = prior[0].dtype
    steps = [1 if _Arrays.view(x, shape).stride(1) == 0 else T for x in given]
    dgiven = [
        torch.empty(B, t, m, dtype=dtype) if w else None for w, t in zip(wanted, steps, strict=True)
    ]
    dprior = [torch.empty(B, m, dtype=dtype) for _ in prior]
    dgamma = torch.empty(B, m, dtype=dtype)
    grads = [None if g is None else g.contiguous() for g in grads]
    mode = _SMOOTHING[smoothing]
    sweeps = 0  # the one-step-lag smoothing of the forward loop, if any
    if smoothing is not None and lag != 1:
        sweeps = _backward_settings(shape, lag, smoothing == "projection")[0]
    buffers = (pointers(grads), pointers(dgiven), pointers(dprior), dgamma.data_ptr())
    _forward_loop("adjoint", rule, gamma, given, prior, shape, velocity, *buffers, mode, sweeps)
    return dgiven, dprior, dgamma


def _smoother(
    name: str, given: Sequence[Tensor], shape: tuple[int, int, int], *settings: int
) -> tuple[Tensor, Tensor]:
    """Runs the compiled smoother loop ``name`` on ``given``; returns the smoothed mean
    ``[B, T, 2m]`` and covariance ``[B, T, 2m, 2m]`` in the general layout."""
    B, T, m = shape
    dtype = given[0].dtype
    mean, cov = fresh((B, T, 2 * m), dtype), fresh((B, T, 2 * m, 2 * m), dtype)
    _smoother_loop(name, given, shape, settings, mean.data_ptr(), cov.data_ptr())
    return mean, cov


def _smoother_loop(
    name: str,
    given: Sequence[Tensor],
    shape: tuple[int, int, int],
    settings: Sequence[int],
    *buffers: object,
) -> None:
    """Calls the compiled function ``name`` (a smoother loop or its adjoint) with a smoother
    loop's arguments, then ``buffers``."""
    inputs = _Arrays(given, shape)
    build.function(name, given[0].dtype)(
        *shape,
        *settings,
        build.threads(shape[0], shape[1]),
        inputs.pointers,
        inputs.strides,
        *buffers,
    )


def _backward_settings(
    shape: tuple[int, int, int], lag: int | None, projection: bool
) -> tuple[int, int]:
    """The compiled backward recursion's settings: how many times it recurses (the steps
    with a successor, or fewer for a fixed lag) and whether Γ is the projection gain."""
    steps = shape[1] - 1
    return (steps if lag is None else min(lag, steps)), int(projection)


def rts_interval(given: Sequence[Tensor], shape: tuple[int, int, int]) -> tuple[Tensor, Tensor]:
    """:func:`torchsvs.kernels.axes_smoother._rts_interval`'s loop: ``given`` the filtered
    ``p, v, a, b, c``, predicted ``p, v, a, b, c`` and ``T`` (``[B, T, m]``-broadcastable);
    returns the smoothed mean ``[B, T, 2m]`` and covariance ``[B, T, 2m, 2m]`` (general
    layout)."""
    return _smoother("rts_interval", given, shape)


def backward(
    given: Sequence[Tensor], shape: tuple[int, int, int], lag: int | None, projection: bool
) -> tuple[Tensor, Tensor]:
    """:func:`torchsvs.kernels.axes_smoother.smooth_axes` after a filter pass: the backward
    recursion with its terms (:func:`~torchsvs.kernels.axes_smoother.backward_terms`) and the
    smoothed moments.
    ``given``: the filter's covariance (3), predicted covariance (3), gain (4), noise
    (unmasked, 3), observed masks (2, as 0/1), ``T``, innovation (2) and mean (2),
    ``[B, T, m]``-broadcastable; the recursion runs from the end (``lag`` None) or ``lag``
    times from zero at each step. Returns the smoothed mean ``[B, T, 2m]`` and covariance
    ``[B, T, 2m, 2m]`` (general layout)."""
    return _smoother("backward", given, shape, *_backward_settings(shape, lag, projection))


def backward_adjoint(
    given: Sequence[Tensor],
    shape: tuple[int, int, int],
    lag: int | None,
    projection: bool,
    grads: Sequence[Tensor | None],
    wanted: Sequence[bool],
) -> list[Tensor | None]:
    """The reverse mode of :func:`backward` (same arguments): ``grads`` the gradients of the
    smoothed mean and covariance (``None``: zero), ``wanted`` which of the 20 inputs need one.
    Returns their gradients ``[B, T, m]`` (``None`` where not wanted; the caller sums them to
    each input's shape)."""
    out = [torch.empty(shape, dtype=given[0].dtype) if w else None for w in wanted]
    held = [None if g is None else g.contiguous() for g in grads]  # alive through the call
    g_mean, g_cov = (None if g is None else g.data_ptr() for g in held)
    settings = _backward_settings(shape, lag, projection)
    _smoother_loop("backward_adjoint", given, shape, settings, g_mean, g_cov, pointers(out))
    return out
