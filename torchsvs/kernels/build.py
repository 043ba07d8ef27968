"""Building and loading the compiled loops: ``cpp/fused.cpp`` (one compiled unit that includes
one header per concern, ``cpp/*.h``), built with the system's C++ compiler on first use and
loaded with :mod:`ctypes`; and what every call into it needs (pointers, output buffers, threads).

The loops themselves: the per-axis kernel's (:mod:`torchsvs.kernels.fused_axes`) and the dense
linear filters' steps (:mod:`torchsvs.kernels.fused_dense`). They run on CPU float32/float64
tensors. Without a compiler the estimators fall back to the tensor loops with one warning;
``TORCHSVS_FUSED=0`` (read when the library is first needed) turns the compiled loops off,
:func:`torchsvs.kernels.eager_loops` does so for a block. The library is built for the
machine's vector width where the compiler allows (:data:`NATIVE`) and cached per source (every
file of ``cpp/``: a changed header rebuilds), compiler, flags, processor and platform under
``$TORCHSVS_CACHE`` (default ``~/.cache/torchsvs``).
"""

from __future__ import annotations

import ctypes
import hashlib
import math
import os
import platform
import shutil
import subprocess
import tempfile
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from torchsvs.kernels import AXIS_KERNEL

#: The C++ sources: the one compiled unit (:data:`UNIT`) and the headers it includes.
SOURCE_DIR = Path(__file__).with_name("cpp")
UNIT = "fused.cpp"
FLAGS = ("-O3", "-std=c++17", "-shared", "-fPIC", "-pthread")
#: Tried first: the build machine's vector width (the library is built where it runs, and cached
#: per processor); no fused multiply-add contraction, so the numbers stay those of the plain
#: build, bit for bit. Without them where the compiler refuses.
NATIVE = ("-march=native", "-ffp-contract=off")
#: Seconds the last build took (0 when the cached library was loaded), for reports.
BUILD = {"seconds": 0.0}

_state: dict[str, ctypes.CDLL | str | None] = {"library": None, "failure": None}


def sources() -> list[Path]:
    """Every file the build reads: ``cpp/fused.cpp`` and the headers beside it, by name."""
    return sorted(p for p in SOURCE_DIR.iterdir() if p.suffix in (".cpp", ".h"))


def source_digest() -> bytes:
    """The sources' names and contents, hashed: part of the cached library's key."""
    digest = hashlib.sha256()
    for path in sources():
        digest.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.digest()


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
        key = hashlib.sha256(source_digest() + built_for.encode()).hexdigest()[:16]
        target = cache_dir() / f"fused-{key}.so"
        if target.exists():
            return target
        target.parent.mkdir(parents=True, exist_ok=True)
        start = time.perf_counter()
        # Built beside the target and renamed: processes building at once never load half a file.
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
            built = Path(tmp) / target.name
            result = subprocess.run(
                [compiler, *flags, str(SOURCE_DIR / UNIT), "-o", str(built)],
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
        curves = getattr(lib, f"kalman_curves_{suffix}")
        curves.argtypes = [*size, ctypes.c_int64, integer, integer, pointers, strides, *(vp,) * 4]
        # the chunk and its sums, the studentized residuals and the leverage they stop at, each
        # step's SURE terms
        curves.argtypes += [ctypes.c_int64, vp, vp, ctypes.c_double, vp]
        getattr(lib, f"lane_width_{suffix}").restype = ctypes.c_int
    imm = lib.turn_imm_f64
    imm.argtypes = [*size, ctypes.c_int64, ctypes.c_int, ctypes.c_int, ctypes.c_void_p, pointers]
    imm.argtypes += [ctypes.c_int64, ctypes.c_int64, pointers]
    imm.restype = ctypes.c_int
    noise = lib.track_noise_f64
    vp, i64, double = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
    noise.argtypes = [*size, ctypes.c_int, vp, vp, vp, vp, i64, i64, *(double,) * 4]
    noise.argtypes += [ctypes.c_int, vp, vp, vp]
    lib.difference_residuals_f64.argtypes = [*size, ctypes.c_int, vp, vp, vp, i64, *(vp,) * 5]
    # N G m p K steps, 11 inputs, the two squared cutoffs, 4 outputs
    sums = lib.trimmed_sums_f64
    sums.argtypes = [*(i64,) * 6, *(vp,) * 11, double, double, *(vp,) * 4]
    sums.restype = ctypes.c_int
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


def lane_width(dtype: torch.dtype) -> int:
    """How many lanes (track axes) of ``dtype`` one vector of the loaded library steps
    together: one register of the machine it was built for (``cpp/lanes.h``); 0 where the
    library is unavailable."""
    if dtype not in _FLOATS or library() is None:
        return 0
    return int(function("lane_width", dtype)())


_HUGE_PAGE = 2 << 20
_ADVISED = 8 * _HUGE_PAGE  # smaller buffers: as torch.empty gives them
_libc: dict[str, ctypes.CDLL | None] = {}


def fresh(shape: Sequence[int], dtype: torch.dtype) -> Tensor:
    """``torch.empty``, with large buffers advised to the kernel as huge pages before their
    first touch: the page faults of a fresh multi-GB output otherwise cost more than
    writing it."""
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


def function(name: str, dtype: torch.dtype) -> Any:
    """The loaded library's function ``name`` for ``dtype`` (float32 or float64)."""
    lib = library()
    assert lib is not None
    return getattr(lib, f"{name}_{'f32' if dtype == torch.float32 else 'f64'}")


def pointers(tensors: Sequence[Tensor | None]) -> ctypes.Array[ctypes.c_void_p]:
    return (ctypes.c_void_p * len(tensors))(*(None if x is None else x.data_ptr() for x in tensors))


def strides(views: Sequence[Tensor]) -> ctypes.Array[ctypes.c_int64]:
    """The element strides of 3-d ``views``, three each, in order (what the loops' ``View``
    reads)."""
    return (ctypes.c_int64 * (3 * len(views)))(*(s for v in views for s in v.stride()))
