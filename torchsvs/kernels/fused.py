"""The per-axis kernel's time loops, and the dense linear filters' steps, compiled:
``fused.cpp``, built with the system's C++ compiler on first use and loaded with :mod:`ctypes`.

:func:`dense_run` is the predict-correct step of a dense linear model (KF, or the SVSF's H⁺
mode with a selection ``H``) per track, over one step (an online ``step`` call: a Python-level
step costs dozens of tensor operations) or a whole run of a model the per-axis kernel does not
cover.

A step of the per-axis recursions (:mod:`torchsvs.kernels.axes`) is a few dozen flops per
track and axis; as tensor operations it costs a few dozen dispatches of about a microsecond
each, so on a dozen long tracks (recorded flights) the loop, not the arithmetic, is the cost.
The compiled loops step blocks of lanes together, take ``[B, T, m]`` views (strides, no
copies) in and write the results in the general layout (what a
:class:`~torchsvs.types.FilterResult` holds) directly, on ``torch.get_num_threads()`` threads
for large batches, into buffers advised as huge pages (:func:`fresh`).

They run on CPU float32/float64 tensors. The per-axis forward loop and the smoother's general
backward recursion have compiled reverse modes too (:func:`adjoint`, :func:`backward_adjoint`,
used by :class:`torchsvs.kernels.axes._CompiledAxes` and ``_CompiledSmoother``), so training
runs them at near inference speed and keeps no graph of small tensors (the RTS fixed interval,
whose own loop :func:`rts_interval` has no reverse mode, trains through the general
recursion). Compiled and tensor loops give the same numbers and gradients up to rounding
(tested to 1e-10 in float64). Without a compiler the estimators fall back to the tensor loops
with one warning; ``TORCHSVS_FUSED=0`` (read when the library is first needed) turns the
compiled loops off, :func:`torchsvs.kernels.eager_loops` does so for a block. The library is
built for the machine's vector width where the compiler allows (:data:`NATIVE`) and cached
per source, compiler, flags, processor and platform under ``$TORCHSVS_CACHE`` (default
``~/.cache/torchsvs``).
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import math
import os
import platform
import shutil
import subprocess
import tempfile
import threading
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import torch
from torch import Tensor

from torchsvs.kernels import AXIS_KERNEL

SOURCE = Path(__file__).with_name("fused.cpp")
FLAGS = ("-O3", "-std=c++17", "-shared", "-fPIC", "-pthread")
#: Tried first: the build machine's vector width (the library is built where it runs, and cached
#: per processor); no fused multiply-add contraction, so the numbers stay those of the plain
#: build, bit for bit. Without them where the compiler refuses.
NATIVE = ("-march=native", "-ffp-contract=off")
#: Seconds the last build took (0 when the cached library was loaded), for reports.
BUILD = {"seconds": 0.0}

_state: dict[str, ctypes.CDLL | str | None] = {"library": None, "failure": None}


def cache_dir() -> Path:
    root = os.environ.get("TORCHSVS_CACHE")
    if root:
        return Path(root)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "torchsvs"


def _compiler() -> str | None:
    for name in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if name and shutil.which(name):
            return name
    return None


def _processor() -> str:
    """What a native build depends on: the processor's feature flags (Linux), else its name."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("flags"):
                return line
    except OSError:
        pass
    return platform.processor()


def _build(compiler: str) -> Path:
    version = subprocess.run(
        [compiler, "--version"], capture_output=True, text=True, check=False
    ).stdout
    failures = []
    for flags in ((*FLAGS, *NATIVE), FLAGS):
        native = flags != FLAGS
        built_for = f"{version} {' '.join(flags)} {platform.machine()} {platform.system()}"
        built_for += _processor() if native else ""
        key = hashlib.sha256(SOURCE.read_bytes() + built_for.encode()).hexdigest()[:16]
        target = cache_dir() / f"fused-{key}.so"
        if target.exists():
            return target
        target.parent.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        # Built beside the target and renamed: processes building at once never load half a file.
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
            built = Path(tmp) / target.name
            result = subprocess.run(
                [compiler, *flags, str(SOURCE), "-o", str(built)],
                capture_output=True,
                text=True,
                check=False,
            )
            if result.returncode == 0:
                os.replace(built, target)
                BUILD["seconds"] = time.perf_counter() - start
                return target
        failures.append(result.stderr.strip()[-2000:])
    raise RuntimeError(f"{compiler} failed: {failures[-1]}")


def library() -> ctypes.CDLL | None:
    """The loaded library, building it if needed; ``None`` when turned off (``TORCHSVS_FUSED=0``
    before it was loaded: an online step asks at every step, an environment look-up costs
    about as much as the step) or unavailable."""
    lib = _state["library"]
    if isinstance(lib, ctypes.CDLL):
        return lib
    if _state["failure"] is not None or os.environ.get("TORCHSVS_FUSED", "1") == "0":
        return None
    compiler = _compiler()
    try:
        if compiler is None:
            raise RuntimeError("no C++ compiler found (set CXX, or install g++)")
        lib = ctypes.CDLL(str(_build(compiler)))
    except (OSError, RuntimeError, subprocess.SubprocessError) as error:
        _state["failure"] = str(error)
        warnings.warn(
            f"torchsvs: compiled per-axis loops unavailable, using tensor loops ({error})",
            RuntimeWarning,
            stacklevel=2,
        )
        return None
    pointers, strides = ctypes.POINTER(ctypes.c_void_p), ctypes.POINTER(ctypes.c_int64)
    size = (ctypes.c_int64,) * 3
    for suffix in ("f32", "f64"):
        vp, integer = ctypes.c_void_p, ctypes.c_int
        loop = [*size, integer, integer, ctypes.c_double, integer, pointers, strides, pointers]
        loop += [strides, pointers]  # the forward loop's arguments and its outputs (or grads)
        getattr(lib, f"forward_{suffix}").argtypes = [*loop, integer]  # and the smoothing
        adjoint = getattr(lib, f"adjoint_{suffix}")
        # the inputs' gradients, then the smoothing and the general recursion's lag (0: none)
        adjoint.argtypes = [*loop, pointers, pointers, vp, integer, ctypes.c_int64]
        smoother = getattr(lib, f"filter_smoother_{suffix}")
        smoother.argtypes = [*loop, ctypes.c_int64, integer]  # the lag, projection
        rts = getattr(lib, f"rts_interval_{suffix}")
        rts.argtypes = [*size, integer, pointers, strides, vp, vp]
        backward = getattr(lib, f"backward_{suffix}")
        backward.argtypes = [*size, ctypes.c_int64, integer, integer, pointers, strides, vp, vp]
        backward_adjoint = getattr(lib, f"backward_adjoint_{suffix}")
        backward_adjoint.argtypes = [*backward.argtypes, pointers]
        dense = getattr(lib, f"dense_run_{suffix}")
        dense.argtypes = [*size, ctypes.c_int64, ctypes.c_int, ctypes.c_double, vp, vp, vp, vp]
        # psi, its strides, F Q H R, the 10 outputs, the totals in and out
        dense.argtypes += [vp, ctypes.c_int64, ctypes.c_int64, pointers, *(vp,) * 12]
        dense.restype = ctypes.c_int
        step = getattr(lib, f"dense_step_{suffix}")
        step.argtypes = [strides, ctypes.c_double, pointers]
        step.restype = ctypes.c_int
    _state["library"] = lib
    return lib


def failure() -> str | None:
    """Why the compiled loops are unavailable (``None``: available or not tried yet)."""
    value = _state["failure"]
    return value if isinstance(value, str) else None


def usable(*tensors: Tensor, differentiable: bool = False) -> bool:
    """Whether the compiled loops can replace the tensor loops for these inputs: CPU, one
    floating dtype (float32/float64), the library available, and no gradient asked for unless
    the loop is ``differentiable`` (has a compiled reverse mode)."""
    dtype = tensors[0].dtype
    if dtype not in _FLOATS or not AXIS_KERNEL["fused"]:
        return False
    grad = torch.is_grad_enabled() and not differentiable
    for x in tensors:  # a plain loop: an online step calls this at every step
        if x.dtype != dtype or x.device.type != "cpu" or (grad and x.requires_grad):
            return False
    return library() is not None


_FLOATS = (torch.float32, torch.float64)


class _Arrays:
    """Pointers and ``[B, T, m]`` element strides of tensors, kept alive for a call."""

    def __init__(self, tensors: Sequence[Tensor], shape: tuple[int, int, int]) -> None:
        views = [self.view(x, shape) for x in tensors]
        self.tensors = views
        self.pointers = _pointers(views)
        self.strides = (ctypes.c_int64 * (3 * len(views)))(*(s for v in views for s in v.stride()))

    @staticmethod
    def view(x: Tensor, shape: tuple[int, int, int]) -> Tensor:
        """``x`` as ``[B, T, m]``; broadcast dimensions get stride 0."""
        if x.ndim == 2:  # per track [B, m]
            x = x.unsqueeze(1)
        elif x.ndim < 2:  # constant, or one value per axis [m]
            x = x.reshape(1, 1, -1)
        return x.expand(shape)


#: Most axes the compiled forward loop steps (``kLanes`` in fused.cpp); more take the tensor loops.
MAX_AXES = 64
_HUGE_PAGE = 2 << 20
_ADVISED = 8 * _HUGE_PAGE  # smaller buffers: as torch.empty gives them
_libc: dict[str, ctypes.CDLL | None] = {}


def fresh(shape: Sequence[int], dtype: torch.dtype) -> Tensor:
    """``torch.empty``, with large buffers advised to the kernel as huge pages before their
    first touch: the page faults of a fresh multi-GB output otherwise cost more than
    writing it (measured 3-4× on a whole-run output)."""
    size = math.prod(shape) * dtype.itemsize
    out = torch.empty(shape, dtype=dtype)
    if size < _ADVISED or platform.system() != "Linux":
        return out
    if "c" not in _libc:
        try:
            loaded = ctypes.CDLL(None, use_errno=True)
            loaded.madvise.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
            _libc["c"] = loaded
        except (OSError, AttributeError):
            _libc["c"] = None
    libc = _libc["c"]
    if libc is not None:
        start = out.data_ptr()
        first = -(-start // _HUGE_PAGE) * _HUGE_PAGE
        last = (start + size) // _HUGE_PAGE * _HUGE_PAGE
        libc.madvise(first, last - first, 14)  # MADV_HUGEPAGE; advice only, failure is fine
    return out


def threads(tracks: int, steps: int) -> int:
    """Threads for a whole-run loop: torch's intra-op count, one below ~100k track-steps (a
    thread's start costs about as much as that work)."""
    return 1 if tracks < 2 or tracks * steps < 100_000 else torch.get_num_threads()


def _function(name: str, dtype: torch.dtype) -> Any:
    """The loaded library's function ``name`` for ``dtype`` (float32 or float64)."""
    lib = library()
    assert lib is not None
    return getattr(lib, f"{name}_{'f32' if dtype == torch.float32 else 'f64'}")


def _pointers(tensors: Sequence[Tensor | None]) -> ctypes.Array[ctypes.c_void_p]:
    return (ctypes.c_void_p * len(tensors))(*(None if x is None else x.data_ptr() for x in tensors))


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
    svsf = rule != "kalman"
    kept = KEPT[keep]
    shapes = ((n,), (n, n), (n,), (n, n), (mz,), (n, mz), (mz, mz), (mz,))
    per_step: list[Tensor | None] = [
        fresh((B, T, *tail), dtype) if i in kept and (svsf or i < 7) else None
        for i, tail in enumerate(shapes)
    ]
    loglik = None if svsf else torch.empty(B, dtype=dtype)
    mask = fresh((B, T, mz), torch.bool) if keep == "all" else None
    last = Last.empty(B, n, mz if svsf else None, dtype)
    smoothed = None
    if smoothing is not None:
        smoothed = fresh((B, T, n), dtype), fresh((B, T, n, n), dtype)
    outputs = (*per_step, loglik, mask, *last, *(smoothed or (None, None)))
    mode = _SMOOTHING[smoothing]
    _forward_loop("forward", rule, gamma, given, prior, shape, velocity, _pointers(outputs), mode)
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
    loglik = torch.empty(B, dtype=dtype) if rule == "kalman" else None
    outputs = (*per_step, loglik, None, *last, *smoothed)
    sweeps, projection = _backward_settings(shape, lag, smoothing == "projection")
    _forward_loop(
        "filter_smoother", rule, gamma, given, prior, shape, velocity, _pointers(outputs),
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
    _function(name, prior[0].dtype)(
        *shape,
        int(rule != "kalman"),
        int(velocity),
        float(gamma),
        threads(B, T),
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
    buffers = (_pointers(grads), _pointers(dgiven), _pointers(dprior), dgamma.data_ptr())
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
    _function(name, given[0].dtype)(
        *shape, *settings, threads(shape[0], shape[1]), inputs.pointers, inputs.strides, *buffers
    )


def _backward_settings(
    shape: tuple[int, int, int], lag: int | None, projection: bool
) -> tuple[int, int]:
    """The compiled backward recursion's settings: how many times it recurses (the steps
    with a successor, or fewer for a fixed lag) and whether Γ is the projection gain."""
    steps = shape[1] - 1
    return (steps if lag is None else min(lag, steps)), int(projection)


def rts_interval(given: Sequence[Tensor], shape: tuple[int, int, int]) -> tuple[Tensor, Tensor]:
    """:func:`torchsvs.kernels.axes._rts_interval`'s loop: ``given`` the filtered
    ``p, v, a, b, c``, predicted ``p, v, a, b, c`` and ``T`` (``[B, T, m]``-broadcastable);
    returns the smoothed mean ``[B, T, 2m]`` and covariance ``[B, T, 2m, 2m]`` (general
    layout)."""
    return _smoother("rts_interval", given, shape)


def backward(
    given: Sequence[Tensor], shape: tuple[int, int, int], lag: int | None, projection: bool
) -> tuple[Tensor, Tensor]:
    """:func:`torchsvs.kernels.axes.smooth_axes` after a filter pass: the backward recursion
    with its terms (:func:`~torchsvs.kernels.axes.backward_terms`) and the smoothed moments.
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
    _smoother_loop("backward_adjoint", given, shape, settings, g_mean, g_cov, _pointers(out))
    return out


#: Largest state or measurement size of :func:`dense_run` (``kMax`` in fused.cpp).
DENSE_MAX = 16


class DenseMatrices:
    """``F, Q, H, R`` of a run of compiled online steps (contiguous, one dtype) and their
    pointers, built once."""

    def __init__(self, matrices: Sequence[Tensor]) -> None:
        self.tensors = list(matrices)
        self.pointers = _pointers(self.tensors)
        self.meas_dim = self.tensors[2].shape[0]  #: rows of H


def dense_run(
    rule: str,
    gamma: float,
    x: Tensor,
    P: Tensor,
    z: Tensor,
    memory: Tensor,
    psi: Tensor,
    matrices: DenseMatrices,
    lead: tuple[int, ...],
    keep: str = "all",
) -> tuple[Tensor | None, ...] | None:
    """Predict-correct steps of a dense linear-Gaussian filter, compiled: ``B`` tracks from
    ``x [B, n]``, ``P [B, n, n]`` over ``z [B, T, m]`` (NaN: missing), the SVSF's ``memory
    [B, m]`` and ``psi`` (``[B, T, m]`` or ``[m]``); all contiguous, one dtype. ``rule``
    ``"kalman"`` or ``"svsf"`` (``H`` with orthonormal rows). ``lead``: the outputs' leading
    shape (``(B, T)``; ``(B,)`` or ``()`` for one step). Returns ``x, P, x_pred, P_pred, e, K,
    S, log_likelihood, e_post, observed`` (with ``keep`` other than ``"all"``: ``None`` for
    those it leaves out, written to a scratch buffer; the covariance, the Kalman rule's
    log-likelihood and the SVSF's ``e_post`` stay, a state needs them), or ``None`` when ``z``
    holds an infinity or a Cholesky factor failed."""
    lib = _state["library"]  # loaded: usable() said so
    assert isinstance(lib, ctypes.CDLL)
    B, n = x.shape
    T, m = z.shape[-2:] if z.ndim == 3 else (1, z.shape[-1])
    dtype = x.dtype
    shapes = ((n,), (n, n), (n,), (n, n), (m,), (n, m), (m, m), (), (m,), (m,))
    # A state needs the covariance, the log-likelihood (Kalman) and the memory (SVSF).
    kept = _KEPT[keep, rule]
    make = fresh if T > 1 else torch.empty  # one step's outputs are small
    out: list[Tensor | None] = [
        make(lead + shape, dtype=torch.bool if i == 9 else dtype) if i in kept else None
        for i, shape in enumerate(shapes)
    ]
    per_track = psi.ndim > 1
    addresses, _scratch_held = _addresses(out, shapes, (lead, dtype, kept))  # held in the call
    call = lib.dense_run_f32 if dtype == torch.float32 else lib.dense_run_f64
    failed = call(
        B,
        T,
        n,
        m,
        0 if rule == "kalman" else 1,
        float(gamma),
        x.data_ptr(),
        P.data_ptr(),
        z.data_ptr(),
        memory.data_ptr(),
        psi.data_ptr(),
        T * m if per_track else 0,
        m if per_track and T > 1 else 0,
        matrices.pointers,
        *addresses,
        None,
        None,
    )
    return None if failed else tuple(out)


class OnlineStep:
    """:func:`dense_run` for one step of ``B`` tracks (results of leading shape ``lead``),
    keeping what ``keep`` keeps, with everything but the step's own tensors formed once: the
    outputs' prototypes, the scratch addresses of those not kept, the call's other arguments
    (in the arrays ``dense_step`` reads). An online step then costs its allocations and one
    call of three arguments (a few µs; filterpy's ``predict`` + ``update`` about 20). One
    thread's: the arguments and scratch are written by every call."""

    def __init__(
        self,
        rule: str,
        gamma: float,
        matrices: DenseMatrices,
        n: int,
        lead: tuple[int, ...],
        dtype: torch.dtype,
        keep: str,
    ) -> None:
        lib = _state["library"]
        assert isinstance(lib, ctypes.CDLL)
        m = matrices.meas_dim
        B = math.prod(lead)
        shapes = ((n,), (n, n), (n,), (n, n), (m,), (n, m), (m, m), (), (m,), (m,))
        self.kept = _KEPT[keep, rule]
        self.prototypes = [
            torch.empty(lead + shapes[i], dtype=torch.bool if i == 9 else dtype) for i in self.kept
        ]
        given: list[Tensor | None] = [None] * 10
        for i, x in zip(self.kept, self.prototypes, strict=True):
            given[i] = x
        outs, self._scratch = _addresses(given, shapes, (lead, dtype, self.kept))
        self.totals = torch.empty(B, dtype=dtype) if rule == "kalman" else None
        self.sizes = (ctypes.c_int64 * 5)(B, n, m, 0 if rule == "kalman" else 1, 0)
        # x, P, z, memory, psi, F, Q, H, R, the outputs, the totals in and out
        self.arguments = (ctypes.c_void_p * 21)(*[None] * 5, *matrices.pointers, *outs)
        # The kept outputs' slots as runs of consecutive ones (a slice assignment each).
        self.runs: list[tuple[int, int, int]] = []  # slot start, output start, output stop
        for j, i in enumerate(self.kept):
            if self.runs and self.runs[-1][0] + j - self.runs[-1][1] == 9 + i:
                self.runs[-1] = (*self.runs[-1][:2], j + 1)
            else:
                self.runs.append((9 + i, j, j + 1))
        self.matrices = matrices  # (alive while its pointers are used)
        call = lib.dense_step_f32 if dtype == torch.float32 else lib.dense_step_f64
        self.call = functools.partial(call, self.sizes, gamma, self.arguments)

    def __call__(
        self, x: Tensor, P: Tensor, z: Tensor, memory: Tensor, psi: Tensor, total: Tensor | None
    ) -> tuple[list[Tensor], Tensor | None] | None:
        """The kept outputs (in :func:`dense_run`'s order) of the step from ``x [B, n]``,
        ``P [B, n, n]`` over ``z [B, m]``, with the SVSF's ``memory [B, m]`` and ``psi`` (``[m]``
        or ``[B, m]``), all contiguous; and the running log-likelihood ``total [B]`` (``None``:
        from 0) plus the step's (Kalman rule; else ``None``). ``None`` as for :func:`dense_run`."""
        out = [torch.empty_like(p) for p in self.prototypes]
        a = self.arguments
        a[0], a[1], a[2], a[3], a[4] = (
            x.data_ptr(),
            P.data_ptr(),
            z.data_ptr(),
            memory.data_ptr(),
            psi.data_ptr(),
        )
        pointers: list[Any] = [y.data_ptr() for y in out]
        for slot, start, stop in self.runs:
            a[slot : slot + stop - start] = pointers[start:stop]
        after = None
        if self.totals is not None:
            after = torch.empty_like(self.totals)
            a[19], a[20] = None if total is None else total.data_ptr(), after.data_ptr()
        self.sizes[4] = psi.shape[-1] if psi.ndim > 1 else 0
        return None if self.call() else (out, after)


#: dense_run's outputs written to tensors, by (keep, rule): those the result and state keep
_KEPT = {
    ("all", "kalman"): (0, 1, 2, 3, 4, 5, 6, 7, 9),
    ("all", "svsf"): tuple(range(10)),
    **{(keep, "kalman"): (0, 1, 7) for keep in ("moments", "mean")},
    **{(keep, "svsf"): (0, 1, 8) for keep in ("moments", "mean")},
}
_scratch = threading.local()  # per thread: a buffer is never written by two calls at once
_SCRATCH_CACHED = 1 << 16  # bytes: one step's outputs; a whole run's are allocated per call


def _addresses(
    outputs: Sequence[Tensor | None],
    shapes: Sequence[tuple[int, ...]],
    key: tuple[tuple[int, ...], torch.dtype, tuple[int, ...]],
) -> tuple[list[int], Tensor | None]:
    """The outputs' addresses, those not kept (``None``) parts of a scratch buffer nobody
    reads (the compiled step reads back what it wrote, so the parts are disjoint); and that
    buffer, which the caller holds through the call. ``key``: the outputs' leading shape,
    dtype and which are kept."""
    lead, dtype, _ = key
    cached = getattr(_scratch, "layouts", {}).get(key)
    if cached is not None:
        offsets, buffer = cached
    else:
        # Sizes in bytes, rounded up to 64 (aligned parts).
        sizes = [-(-math.prod(lead) * math.prod(s) * dtype.itemsize // 64) * 64 for s in shapes]
        offsets, total = [], 0
        for x, size in zip(outputs, sizes, strict=True):
            offsets.append(total if x is None else -1)
            total += size if x is None else 0
        buffer = torch.empty(total, dtype=torch.uint8) if total else None
        if total <= _SCRATCH_CACHED:
            _scratch.__dict__.setdefault("layouts", {})[key] = (offsets, buffer)
    base = 0 if buffer is None else buffer.data_ptr()
    return [
        base + at if x is None else x.data_ptr() for x, at in zip(outputs, offsets, strict=True)
    ], buffer
