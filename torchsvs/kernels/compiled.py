"""The Gaussian filters' predict-correct step compiled with ``torch.compile``.

Every Gaussian filter (KF, EKF, UKF, SVSF, RSTKF, SIF) runs its time loop in Python around one
function, :meth:`~torchsvs.filters.gaussian.GaussianFilter.filter_step`: a few dozen to a few
hundred small tensor operations per step, each paying a dispatch (where the C++ loops of
:mod:`~torchsvs.kernels.fused_axes` and :mod:`~torchsvs.kernels.fused_dense` apply, linear
models without gradients, they run instead).
Within :func:`torchsvs.kernels.compiled_steps` a chunk of ``chunk`` steps (default 4) is
compiled once per estimator, shapes, dtype and grad mode (inductor, with its C++ wrapper:
:data:`INDUCTOR_OPTIONS`), and every chunk of a run, and of later runs, calls the same compiled
function on views of the run's tensors (``Prepared.window``, ``Inputs.window``). The time loop
itself stays in Python: the unrolled sequence is never traced, so compile time does not grow
with ``T``.

* Bounded compile time: ``dynamic=False`` and ``fullgraph=True``; one compiled function per
  estimator and key (backend, dtype, grad mode, batch, which inputs vary per step, chunk
  length, the covariance's batch), each with a code object of its own so that Dynamo's
  recompile limit applies per key and nothing recompiles per step. The first step of a fresh
  run stays eager: it turns a shared prior (``P0 [1, n, n]``) and the absent first memory into
  the shapes every later step has; so do the last steps that fill no chunk. A run thus
  compiles once. Every compilation is timed into :data:`STATS` and logged at INFO level by the
  ``torchsvs.kernels.compiled`` logger.
* Same numbers: the compiled step is the eager one traced (no second formula). Its only data-
  dependent branch, the Cholesky jitter of :func:`torchsvs.linalg.cholesky`, becomes
  branch-free while traced: a failed factor is NaN, and a step whose results are not all finite
  runs again eagerly (jitter, error) from the same inputs. Gradients flow through the compiled
  forward and backward graphs (AOTAutograd).
* Fallback: if compiling fails (no C++ compiler for inductor, a Dynamo error) the steps run
  eagerly with one ``RuntimeWarning``; ``TORCHSVS_COMPILE=0`` turns compiled steps off
  everywhere, also under a user's ``torch.compile``.
* A user's ``torch.compile(estimator)`` (or of ``scan``/``step``): the estimator call leaves
  Dynamo (:func:`outside_dynamo`; its Python time loop would be unrolled, and input checks
  break the graph) and runs its time loop eagerly with compiled steps.

Where it pays: a compiled step is faster than the eager one, but its compilation costs far
more than a single run saves, and is repaid only after many runs (the measurements, per filter,
batch, dtype and pass: ``benchmarks/compiled_steps.md``, from ``python -m
benchmarks.compiled_steps``). Hence compiled steps are opt-in, for many runs in one process
(training, evaluation sweeps, streams of tracks): outside :func:`torchsvs.kernels.compiled_steps`
the steps run eagerly, and ``TORCHSVS_COMPILE=0`` keeps them eager even within it. Online
:meth:`~torchsvs.estimator.SteppedEstimator.step` calls are one-step runs: they compile with
``chunk=1`` only (a longer chunk never fills).
"""

from __future__ import annotations

import functools
import logging
import os
import time
import types
import warnings
import weakref
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

import torch
from torch import Tensor

from torchsvs import linalg
from torchsvs.kernels import COMPILED_STEPS

log = logging.getLogger(__name__)

#: Compilations so far: how many, their total and last wall-clock seconds (the first call of a
#: cache key: tracing, compiling and running one step), for reports.
STATS = {"compiles": 0, "seconds": 0.0, "last": 0.0}

#: One predict-correct cycle's results: ``(x̂_{t|t-1}, P_{t|t-1}, F_t, Step)``.
StepOut = tuple[Tensor, Tensor, Tensor, Any]
#: Runs the steps from ``t`` (as many as the runner chooses, at least one) from ``x``, ``P``
#: and the corrector's carried memory.
Runner = Callable[[int, Tensor, Tensor, "Tensor | None"], list[StepOut]]

#: Inductor's settings for a step: its generated call in C++, since a step of small matrices
#: is dozens of tiny kernels whose calls from Python would cost more than their work.
INDUCTOR_OPTIONS: dict[str, str | int | bool | Callable[..., Any]] = {"cpp_wrapper": True}

_failures: dict[str, str | None] = {"warned": None}
#: estimator → cache key → its compiled chunk (None where compiling failed)
_cache: weakref.WeakKeyDictionary[Any, dict[tuple[Any, ...], _Chunk | None]] = (
    weakref.WeakKeyDictionary()
)


def active() -> bool:
    """Whether compiled steps are on (:func:`torchsvs.kernels.compiled_steps`, not turned off
    by ``TORCHSVS_COMPILE=0``)."""
    return bool(COMPILED_STEPS["enabled"]) and os.environ.get("TORCHSVS_COMPILE", "1") != "0"


def clear() -> None:
    """Forgets every compiled step and failure (the next run compiles, and may warn, again)."""
    _cache.clear()
    _failures["warned"] = None


def runner(estimator: Any, prep: Any, inputs: Any, fresh: bool) -> Runner:
    """What runs a prepared run's steps (``prep``: ``estimator.prepare(inputs)``; ``fresh``:
    from ``init``'s state): its ``filter_step`` one at a time, or compiled chunks of them when
    :func:`active`."""

    def eager(t: int, x: Tensor, P: Tensor, carried: Tensor | None) -> list[StepOut]:
        return [estimator.filter_step(t, x, P, carried, prep, inputs)]

    if not active() or estimator.covariance_form != "joseph":
        # (a factored covariance form hands its factor from step to step: eager)
        return eager
    chunk = max(1, int(COMPILED_STEPS["chunk"]))
    T = inputs.steps
    layout = tuple(
        None if v is None else v.ndim
        for v in (prep.H, prep.R, prep.F, prep.Q, inputs.dt, inputs.u, inputs.psi)
    )
    run_key = (
        str(COMPILED_STEPS["backend"]),
        inputs.z.dtype,
        torch.is_grad_enabled(),
        inputs.batch,
        prep.any_missing,
        layout,
    )

    def compiled(t: int, x: Tensor, P: Tensor, carried: Tensor | None) -> list[StepOut]:
        if (fresh and t == 0) or t + chunk > T:
            # A fresh run's first step, and the steps that do not fill a chunk: eager (the
            # module's notes), so that a run compiles once.
            return eager(t, x, P, carried)
        key = (*run_key, chunk, P.shape[0], carried is None)
        args = (estimator, x, P, carried, prep.window(t, t + chunk), inputs.window(t, t + chunk))
        out = _call(estimator, key, args)
        # Not compiled, or not finite: eagerly (the jitter, or the same non-finite numbers).
        return _run_window(*args) if out is None else out

    return compiled


def _run_window(
    estimator: Any, x: Tensor, P: Tensor, carried: Tensor | None, prep: Any, inputs: Any
) -> list[StepOut]:
    """Every step of a window (``prep.window``, ``inputs.window``) from ``x``, ``P``,
    ``carried``: what is compiled, and its eager reference."""
    out = []
    for t in range(prep.z.shape[1]):
        step_out = estimator.filter_step(t, x, P, carried, prep, inputs)
        step = step_out[3]
        x, P, carried = step.mean, step.cov, step.post_innovation
        out.append(step_out)
    return out


def _checked_window(*args: Any) -> tuple[list[StepOut], Tensor]:
    """:func:`_run_window` and whether all its results are finite (a failed Cholesky factor
    is NaN in a compiled step: :data:`torchsvs.linalg.BRANCH_FREE`)."""
    out = _run_window(*args)
    values = [v for x_pred, P_pred, F_t, step in out for v in (x_pred, P_pred, F_t, *step)]
    finite = torch.stack([torch.isfinite(v).all() for v in values if isinstance(v, Tensor)])
    return out, finite.all()


class _Chunk:
    """One compiled window function and whether its first call (the compilation) is done."""

    def __init__(self) -> None:
        code = _checked_window.__code__.replace()  # a code object, hence a Dynamo cache, of its own
        fresh = types.FunctionType(code, _checked_window.__globals__, "compiled_step")
        backend = COMPILED_STEPS["backend"]
        options = INDUCTOR_OPTIONS if backend == "inductor" else None
        self.fn = torch.compile(
            fresh, backend=backend, dynamic=False, fullgraph=True, options=options
        )
        self.compiled = False


def _call(estimator: Any, key: tuple[Any, ...], args: tuple[Any, ...]) -> list[StepOut] | None:
    """The compiled window of ``key`` on ``args``; ``None`` where it is not available (its
    compilation failed: one warning) or its results are not all finite."""
    chunks = _cache.setdefault(estimator, {})
    try:
        if key not in chunks:
            chunks[key] = _Chunk()
        chunk = chunks[key]
        if chunk is None:
            return None
        start = time.perf_counter()
        with _compiled_call(compiling=not chunk.compiled):
            out, finite = chunk.fn(*args)
        if not chunk.compiled:
            chunk.compiled = True
            seconds = time.perf_counter() - start
            STATS["compiles"] += 1
            STATS["seconds"] += seconds
            STATS["last"] = seconds
            log.info("compiled %s steps %s in %.1f s", type(estimator).__name__, key, seconds)
    except Exception as error:  # any failure to compile (or a step's own): the eager step says
        chunks[key] = None
        _warn(estimator, error)
        return None
    return out if bool(finite) else None


def _warn(estimator: Any, error: Exception) -> None:
    if _failures["warned"] is None:
        _failures["warned"] = f"{type(error).__name__}: {error}"
        message = str(error).strip().splitlines()[0][:300] if str(error).strip() else ""
        warnings.warn(
            f"torchsvs: compiled steps unavailable for {type(estimator).__name__}, running "
            f"eager steps ({type(error).__name__}: {message})",
            RuntimeWarning,
            stacklevel=4,
        )


#: Warnings torch's compiler stack emits about its own internals while it compiles (not about
#: the user's code): Dynamo reads ``.grad`` of the non-leaf tensors it fakes, inductor calls a
#: deprecated check and imports a deprecated TorchScript decorator.
_COMPILER_NOISE = (
    ("The .grad attribute of a Tensor that is not a leaf Tensor", UserWarning),
    ("`torch._prims_common.check` is deprecated", FutureWarning),
    ("`torch.jit.script_method` is deprecated", DeprecationWarning),
)


@contextmanager
def _compiled_call(compiling: bool) -> Iterator[None]:
    """Around a compiled window's call: :func:`~torchsvs.linalg.cholesky` branch-free (the
    traced step's assumption, a guard of the compiled function), and while it compiles, the
    compiler's noise (:data:`_COMPILER_NOISE`) silenced."""
    linalg.BRANCH_FREE["cholesky"] = True
    try:
        if compiling:
            with warnings.catch_warnings():
                for message, category in _COMPILER_NOISE:
                    warnings.filterwarnings("ignore", message=message, category=category)
                yield
        else:
            yield
    finally:
        linalg.BRANCH_FREE["cholesky"] = False


Method = TypeVar("Method", bound=Callable[..., Any])


def outside_dynamo(method: Method) -> Method:
    """``method`` (an estimator's ``forward``, ``scan``, ``step``), which leaves Dynamo when a
    user's ``torch.compile`` traces it: the call then runs its time loop eagerly, with compiled
    steps (:func:`torchsvs.kernels.compiled_steps`; ``TORCHSVS_COMPILE=0`` still turns them
    off), instead of Dynamo unrolling the loop."""

    def with_compiled_steps(*args: Any, **kwargs: Any) -> Any:
        before = COMPILED_STEPS["enabled"]
        COMPILED_STEPS["enabled"] = True
        try:
            return method(*args, **kwargs)
        finally:
            COMPILED_STEPS["enabled"] = before

    @functools.wraps(method)
    def call(*args: Any, **kwargs: Any) -> Any:
        if torch.compiler.is_compiling():
            # Disabled here, under a trace, not when decorating: torch.compiler.disable imports
            # Dynamo, seconds of every command's start that never compiles anything.
            return torch.compiler.disable(with_compiled_steps)(*args, **kwargs)
        return method(*args, **kwargs)

    return call  # type: ignore[return-value]
