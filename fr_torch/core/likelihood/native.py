"""Fused CPU kernels, built on first use: the measure-b grid scores and the refinement's step.

:func:`measure_b_scores` computes :func:`fr_torch.core.likelihood.objective.objective_b_nograd`'s objective
(B, H) float64 and :func:`measure_b_grad` the refinement's objective with its gradient
(``measure_b_forward`` + ``measure_b_backward``), bit for bit, without storing the (B, 2N, 3H)
deviations: ``kernels_measure_b.c`` scores a tile of hypotheses a few segments at a time in
buffers that stay in the L1 cache, with
the same float32 operations in the same order as the torch path, ``atan`` / ``exp`` / ``log`` from
the same MKL VML routines torch's CPU kernels call, and the exact fixed-point sum over segments
(:func:`fr_torch.core.exact.exact_sum`: every order of the integer additions gives the same sum).

Building and trusting them:

* The C file is compiled once per machine with the system's C compiler (``cc``, :data:`FLAGS`:
  ``-O3 -ffp-contract=off``, no fast math, every product and sum rounded once, as torch's; plus
  ``-mavx2`` on a CPU with AVX2) into ``$FR_NATIVE_CACHE`` (default ``~/.cache/fr_torch/native``),
  named by a hash of the source, the flags, the compiler and the torch version: about 1 s, once.
  Later processes load the cached library.
* Before first use in a process the kernels are checked against the torch path on random segments
  and vanishing points (:func:`fr_torch.core.likelihood.mixture.kernels_match_torch`, registered by that
  module through :func:`register_check`);
  one differing bit and it is not used.
* Without a C compiler, without MKL in torch (torch's ``atan`` / ``exp`` / ``log`` are then other
  routines), with ``FR_NATIVE=0``, or when the check fails, :func:`available` is False and the
  torch path runs: the same bits, slower.  ``tests/test_reproducibility.py`` runs both paths.

Threads: the work items (image, tile of up to 256 hypotheses; an image for the gradient) are split
into ``torch.get_num_threads()`` contiguous ranges, each scored by one call from a worker thread
with MKL single-threaded (ctypes releases the GIL); every item's result is its own, so the split
cannot change a bit.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import threading
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch

SOURCE = Path(__file__).with_name("kernels_measure_b.c")
#: -ffp-contract=off: no fused multiply-add, every product and sum rounded once (torch's CPU kernels
#: round alike); -fno-trapping-math only lets comparisons be vectorised (values unchanged).
FLAGS = ("-O3", "-ffp-contract=off", "-fno-fast-math", "-fno-trapping-math", "-fPIC", "-shared")
TILE = 256  # at most this many hypotheses per work item: kernels_measure_b.c

_state: dict = {}
_lock = threading.Lock()


def _cache_dir() -> Path:
    root = os.environ.get("FR_NATIVE_CACHE")
    if root:
        return Path(root)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "fr_torch" / "native"


def _torch_cpu_library() -> ctypes.CDLL | None:
    """torch's own CPU library (already loaded by ``import torch``), whose MKL VML entry points
    (``vsAtan``, ``vsExp``, ``vsLn``) torch's float32 ``atan`` / ``exp`` / ``log`` call."""
    folder = Path(torch.__file__).parent / "lib"
    for name in ("libtorch_cpu.so", "libtorch_cpu.dylib"):
        if (folder / name).is_file():
            try:
                return ctypes.CDLL(str(folder / name))
            except OSError:
                return None
    return None


def _cpu_flags() -> tuple[str, ...]:
    """``-mavx2`` where the CPU has AVX2 (the arithmetic loops run 8 floats at a time: about a
    quarter faster; the same bits, as no fused multiply-add is allowed), else nothing."""
    try:
        with open("/proc/cpuinfo") as info:
            return ("-mavx2",) if "avx2" in info.read().split() else ()
    except OSError:
        return ()


def _build() -> Path:
    """The compiled library, built into the cache when not already there (the name holds a hash
    of the source, the flags, the compiler and torch's version, so a machine with other CPU flags
    builds its own)."""
    source = SOURCE.read_bytes()
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        raise RuntimeError("no C compiler")
    errors = []
    for flags in dict.fromkeys((FLAGS + _cpu_flags(), FLAGS)):  # without -mavx2 if the compiler refuses it
        key = hashlib.sha256(source + " ".join(flags).encode() + torch.__version__.encode()
                             + compiler.encode()).hexdigest()[:16]
        target = _cache_dir() / f"measure_b-{key}.so"
        if target.is_file():
            return target
        target.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
            built = Path(tmp) / target.name
            done = subprocess.run([compiler, *flags, "-o", str(built), str(SOURCE), "-lm"], capture_output=True,
                                  text=True, timeout=120)
            if done.returncode == 0:
                os.replace(built, target)  # atomic: concurrent builders leave one complete file
                return target
            errors.append(done.stderr.strip()[-500:])
    raise RuntimeError(f"{compiler} failed: {errors[-1]}")


def _load():
    if not torch.backends.mkl.is_available():
        raise RuntimeError("torch without MKL: its atan / exp / log are not the routines this kernel calls")
    torch_cpu = _torch_cpu_library()
    if torch_cpu is None:
        raise RuntimeError("torch's CPU library not found")
    vml = [ctypes.cast(getattr(torch_cpu, name), ctypes.c_void_p).value for name in ("vsAtan", "vsExp", "vsLn")]
    _state["mkl_threads"] = torch_cpu.MKL_Set_Num_Threads_Local  # MKL's thread count in the calling thread (C API)
    _state["mkl_threads"].argtypes, _state["mkl_threads"].restype = [ctypes.c_int], ctypes.c_int
    library = ctypes.CDLL(str(_build()))
    scores = library.fr_measure_b_scores
    scores.restype = None
    scores.argtypes = ([ctypes.c_int64] * 8 + [ctypes.c_void_p] * 5 + [ctypes.c_float] * 2
                       + [ctypes.c_void_p] * 4)
    grad = library.fr_measure_b_grad
    grad.restype = ctypes.c_int
    grad.argtypes = ([ctypes.c_int64] * 5 + [ctypes.c_void_p] * 6 + [ctypes.c_float] * 2
                     + [ctypes.c_void_p] * 6)
    return {"scores": scores, "grad": grad}, vml


def register_check(check) -> None:
    """The test every process runs before trusting the kernels: ``check()`` -> True when they give
    the torch path's bits (:func:`fr_torch.core.likelihood.mixture.kernels_match_torch`, registered when
    that module loads; without one the kernels are not used)."""
    _state["check"] = check


def available() -> bool:
    """True when the fused kernel is built, loaded and checked in this process (the first call
    does that; module docstring).  ``FR_NATIVE=0`` turns it off."""
    if os.environ.get("FR_NATIVE", "1") == "0" or "check" not in _state:  # the check comes with likelihood/mixture.py
        return False
    if "ok" not in _state:
        with _lock:
            if "ok" not in _state:
                try:
                    _state["functions"], _state["vml"] = _load()
                    _state["ok"] = True
                    _state["ok"] = bool(_state["check"]())
                    if not _state["ok"]:
                        warnings.warn("fR: the fused CPU kernel does not reproduce the torch path here; "
                                      "running without it", RuntimeWarning, stacklevel=2)
                except Exception as exc:  # no compiler, no MKL symbols, a failed build: the torch path
                    _state["ok"] = False
                    _state["error"] = f"{type(exc).__name__}: {exc}"
    return _state["ok"]


def _pool() -> ThreadPoolExecutor:
    """The kernels' worker threads (one per core at most, started on demand), each with MKL
    single-threaded: the kernels' MKL calls are short, and MKL's own threads for each of them (its
    default outside torch's parallel regions) cost several times the work.  Only these threads get
    that setting; torch's keep theirs."""
    pool = _state.get("pool")
    if pool is None or _state.get("pool_pid") != os.getpid():  # a forked child has none of its parent's threads
        set_mkl_threads = _state["mkl_threads"]
        pool = _state["pool"] = ThreadPoolExecutor(max_workers=max(1, os.cpu_count() or 1),
                                                   thread_name_prefix="fr-native",
                                                   initializer=lambda: set_mkl_threads(1))
        _state["pool_pid"] = os.getpid()
    return pool


def measure_b_scores(line_along: torch.Tensor, factor: torch.Tensor, scale: torch.Tensor, flat: torch.Tensor,
                     neg_inv_scale: torch.Tensor, log_coef: torch.Tensor, background: float, floor: float,
                     vertical_axis: int, vertical_block: int = 1) -> torch.Tensor:
    """Measure-b objective (B, H) float64 (:func:`fr_torch.core.likelihood.objective.objective_b_nograd`'s,
    bit for bit) in one fused pass; call only when :func:`available`.

    ``line_along`` (B, 2N, 3) float32; ``factor`` (B, N) float32 and ``scale`` (B,) float64 the
    exact sum's weight times scale and scale (:func:`fr_torch.core.exact.exact_sum`); ``flat``
    (B, 3, 3H) float32 VP-major vanishing points; ``neg_inv_scale``, ``log_coef`` (3, 1) float32;
    ``background`` the background density and ``floor`` the exponent floor (as float32);
    ``vertical_block`` as in ``objective_b_nograd`` (must divide H).
    """
    function, vml = _state["functions"]["scores"], _state["vml"]
    batch, n_seg = factor.shape
    hyp = flat.shape[2] // 3
    line_along = line_along.contiguous()
    factor = factor.contiguous()
    scale = scale.to(torch.float64).contiguous()
    flat = flat.contiguous()
    coef = torch.stack([neg_inv_scale.reshape(3), log_coef.reshape(3)], 1).to(torch.float32).contiguous()
    out = torch.empty(batch, hyp, dtype=torch.float64)
    if not 1 <= vertical_block <= TILE or hyp % vertical_block:
        raise ValueError(f"vertical_block {vertical_block} must divide the {hyp} hypotheses (and be <= {TILE})")
    tile = TILE - TILE % vertical_block  # whole runs of the vertical VP
    tiles = -(-hyp // tile)
    items = batch * tiles

    def run(first: int, last: int) -> None:
        function(first, last, tiles, tile, n_seg, hyp, vertical_block, vertical_axis,
                 line_along.data_ptr(), factor.data_ptr(), scale.data_ptr(), flat.data_ptr(), coef.data_ptr(),
                 background, floor, *vml, out.data_ptr())

    _in_threads(run, items)
    return out


def _in_threads(run, items: int) -> None:
    """``run(first, last)`` over ``items`` work items, split into contiguous ranges over
    ``torch.get_num_threads()`` of the kernels' threads (:func:`_pool`; ctypes calls release the
    GIL), one range even for one thread (the calling thread's MKL may be multi-threaded)."""
    threads = max(1, min(torch.get_num_threads(), items))
    bounds = [items * k // threads for k in range(threads + 1)]
    for future in [_pool().submit(run, bounds[k], bounds[k + 1]) for k in range(threads)]:
        future.result()


def measure_b_grad(line_along: torch.Tensor, weight: torch.Tensor, factor: torch.Tensor, scale: torch.Tensor,
                   flat: torch.Tensor, neg_inv_scale: torch.Tensor, log_coef: torch.Tensor, background: float,
                   floor: float, vertical_axis: int, grad_out: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The refinement's measure-b objective (B, H) float64 and its gradient with respect to the
    VP-major vanishing points, (B, 3, 3H) float64, for the upstream gradient ``grad_out`` (B, H):
    :func:`fr_torch.core.likelihood.objective.measure_b_forward` then ``measure_b_backward``, bit for bit, in
    one pass per image; call only when :func:`available`.  Arguments as for
    :func:`measure_b_scores`, plus ``weight`` (B, N) float32."""
    function, vml = _state["functions"]["grad"], _state["vml"]
    batch, n_seg = weight.shape
    hyp = flat.shape[2] // 3
    line_along, weight, factor = line_along.contiguous(), weight.contiguous(), factor.contiguous()
    scale = scale.to(torch.float64).contiguous()
    flat = flat.contiguous()
    grad_out = grad_out.to(torch.float32).expand(batch, hyp).contiguous()
    coef = torch.stack([neg_inv_scale.reshape(3), log_coef.reshape(3)], 1).to(torch.float32).contiguous()
    objective = torch.empty(batch, hyp, dtype=torch.float64)
    grad = torch.empty(batch, 3, 3 * hyp, dtype=torch.float64)

    def run(first: int, last: int) -> None:
        if function(first, last, n_seg, hyp, vertical_axis, line_along.data_ptr(), weight.data_ptr(),
                    factor.data_ptr(), scale.data_ptr(), flat.data_ptr(), coef.data_ptr(), background, floor,
                    grad_out.data_ptr(), *vml, objective.data_ptr(), grad.data_ptr()):
            raise MemoryError("fr_measure_b_grad: out of memory")

    _in_threads(run, batch)
    return objective, grad
