"""Fused CPU kernels, built on first use: the measure-b grid scores, the refinement's gradient and
the whole refinement loop.

:func:`measure_b_scores` computes :func:`fr_torch.core.likelihood.objective.objective_b_nograd`'s objective
(B, H) float64, :func:`measure_b_grad` the refinement's objective with its gradient
(``measure_b_forward`` + ``measure_b_backward``) and :func:`measure_b_refine` every Adam step of a
refinement (:func:`fr_torch.core.search.refine.refine_fused`: parameters to vanishing points, the
gradient, the chain rule to the parameters, the focal prior, Adam and the box; with the division
model also each hypothesis' segments undistorted with its k, the chain rule to k and the prior on
k), bit for bit, without storing the (B, 2N, 3H) deviations: ``kernels_measure_b.c`` scores a tile
of hypotheses a few segments at a time in buffers that stay in the L1 cache, with the same float32
operations in the same order as the torch path, ``atan`` / ``exp`` / ``log`` / ``sin`` / ``cos``
spelled out as :mod:`fr_torch.core.exact_math` writes them (no maths library: the same bits on every
CPU), ``sqrt`` correctly rounded, and the exact fixed-point sum over segments
(:func:`fr_torch.core.exact.exact_sum`: every order of the integer additions gives the same sum).

Building and trusting them:

* The C file is compiled once per machine with the system's C compiler (``cc``, :data:`FLAGS`:
  ``-O3 -ffp-contract=off``, no fast math, every product and sum rounded once, as torch's; plus
  ``-mavx2`` on a CPU with AVX2, :func:`_cpu_flags`) into ``$FR_NATIVE_CACHE`` (default ``~/.cache/fr_torch/native``),
  named by a hash of the source, the flags, the compiler and the torch version: about 1 s, once.
  Later processes load the cached library.
* Before first use in a process the kernels are checked against the torch path on random segments
  and vanishing points (:func:`fr_torch.core.likelihood.mixture.kernels_match_torch`, registered by that
  module through :func:`register_check`), the refinement loop on random scenes
  (:func:`fr_torch.core.search.refine.refine_kernel_matches_torch`, registered as ``"refine"``), the
  division model's refinement loop (the same check with the division model's segments, registered by
  :mod:`fr_torch.core.search.lens` as ``"refine_lens"``); one differing bit and that kernel is not used.
  Each verdict is recorded beside the library (:func:`_verdict_file`, named by a hash of the
  library, the torch path's sources, the CPU and the settings that pick library code): a later
  process on the same machine, code and settings takes it instead of checking again (the same
  check gives the same bits); delete the file to check again.
* The same library holds :mod:`fr_torch.core.exact_math`'s functions as loops over whole tensors
  (``fr_elementary_f32`` / ``_f64``); when the library loads and these loops give ``exact_math``'s
  written-out bits (:func:`elementary_match_torch`), they are handed to it
  (``exact_math.register_compiled``) before the kernels' checks run: the torch code outside the
  kernels, the checks' torch path included, calls them.
* Without a C compiler, with ``FR_NATIVE=0``, or when the check fails, :func:`available` is False
  and the torch path runs: the same bits, slower.  ``tests/test_reproducibility.py`` runs both paths.

Threads: the work items (image, tile of up to 256 hypotheses; an image for the gradient and the
refinement) are split into ``torch.get_num_threads()`` contiguous ranges, each scored by one call
from a worker thread (ctypes releases the GIL); every item's result is its
own, so the split cannot change a bit.  One image's refinement stays on one thread: its hypotheses
share the gradient's fixed-point grid at every step, and threads meeting once per step ran slower
than one thread on a busy machine; the division model's hypotheses do not (each is its own virtual
image), but splitting them over two threads on a busy machine also ran slower than one thread.
"""
from __future__ import annotations

import ctypes
import hashlib
import json
import math
import os
import platform
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
_checks: dict = {}
_lock = threading.RLock()


def _cache_dir() -> Path:
    root = os.environ.get("FR_NATIVE_CACHE")
    if root:
        return Path(root)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "fr_torch" / "native"


def _torch_cpu_library() -> ctypes.CDLL | None:
    """torch's own CPU library (already loaded by ``import torch``), where its oneMKL lives."""
    folder = Path(torch.__file__).parent / "lib"
    for name in ("libtorch_cpu.so", "libtorch_cpu.dylib"):
        if (folder / name).is_file():
            try:
                return ctypes.CDLL(str(folder / name))
            except OSError:
                return None
    return None


#: oneMKL's code branches (``MKL_CBWR_*`` constants of ``mkl_cbwr_get``) by number.
MKL_BRANCHES = {3: "COMPATIBLE", 4: "SSE2", 6: "SSSE3", 7: "SSE4_1", 8: "SSE4_2", 9: "AVX", 10: "AVX2",
                11: "AVX512_MIC", 12: "AVX512", 13: "AVX512_MIC_E1", 14: "AVX512_E1"}


def mkl_branch() -> str | None:
    """The oneMKL code branch torch's CPU library runs here: the one ``MKL_CBWR`` pins, else the one
    MKL picks for this CPU (``"AVX512_E1"``, ``"AVX2"``, ...); None without MKL in torch.

    MKL's vector maths (torch's CPU ``exp``, ``log``, ``atan``, ``sqrt``, ...) rounds differently on
    different branches; the search takes these functions from :mod:`fr_torch.core.exact_math`
    instead, and measurement records (``fr_eval.machine``) name the branch so that a difference
    left elsewhere can be traced."""
    library = _torch_cpu_library()
    try:
        get, auto = library.mkl_serv_cbwr_get, library.mkl_serv_cbwr_get_auto_branch
    except AttributeError:  # no library, or no MKL in it
        return None
    pinned = get(1)  # MKL_CBWR_BRANCH: 1 = not pinned
    number = auto() if pinned <= 2 else pinned
    return MKL_BRANCHES.get(number, str(number))


def _cpu_flags() -> tuple[str, ...]:
    """``-mavx2`` where the CPU has AVX2 (the arithmetic loops run 8 floats at a time: about a
    quarter faster), and ``FR_WIDE`` where it has AVX-512 (the elementary functions' loops in
    512-bit vectors: the grid's scores about a quarter faster; the whole file in AVX-512 made the
    refinement's short loops 2.7 times slower); the same bits either way, as no fused multiply-add
    is allowed.  Nothing on other CPUs."""
    try:
        with open("/proc/cpuinfo") as info:
            flags = set(info.read().split())
    except OSError:
        return ()
    chosen = ("-mavx2",) if "avx2" in flags else ()
    if chosen and {"avx512f", "avx512dq", "avx512vl"} <= flags:
        chosen += ("-DFR_WIDE=1",)
    return chosen


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
    _state["library"] = _build()
    library = ctypes.CDLL(str(_state["library"]))
    scores = library.fr_measure_b_scores
    scores.restype = None
    scores.argtypes = ([ctypes.c_int64] * 8 + [ctypes.c_void_p] * 5 + [ctypes.c_float] * 2
                       + [ctypes.c_void_p])
    grad = library.fr_measure_b_grad
    grad.restype = ctypes.c_int
    grad.argtypes = ([ctypes.c_int64] * 5 + [ctypes.c_void_p] * 6 + [ctypes.c_float] * 2
                     + [ctypes.c_void_p] * 3)
    refine = library.fr_measure_b_refine
    refine.restype = None
    refine.argtypes = ([ctypes.c_int64] * 6 + [ctypes.c_void_p] * 3
                       + [ctypes.c_float] * 2 + [ctypes.c_void_p] * 5 + [ctypes.c_float] * 2 + [ctypes.c_void_p]
                       + [ctypes.c_float] * 6 + [ctypes.c_int64] + [ctypes.c_void_p] * 5)
    work = library.fr_refine_work_floats
    work.restype, work.argtypes = ctypes.c_int64, [ctypes.c_int64] * 3
    functions = {"scores": scores, "grad": grad, "refine": refine, "refine_work": work}
    for dtype, name in ((torch.float32, "fr_elementary_f32"), (torch.float64, "fr_elementary_f64")):
        functions[dtype] = getattr(library, name)
        functions[dtype].restype, functions[dtype].argtypes = None, [ctypes.c_int64] * 2 + [ctypes.c_void_p] * 2
    return functions


#: The compiled elementary loops' operation codes, by dtype (fr_elementary_f32 / _f64 of kernels_measure_b.c).
_ELEMENTARY = {torch.float32: {"atan": 0, "exp": 1, "log": 2, "sqrt": 3, "sin_cos": 4},
               torch.float64: {"atan": 0, "exp": 1, "log": 2, "sqrt": 3, "sin_cos": 4, "tan": 5}}


def _elementary(name: str, dtype: torch.dtype = torch.float32):
    """``f(x)`` for a CPU tensor of ``dtype`` through the compiled loop ``name`` of :data:`_ELEMENTARY`
    (one call in the calling thread, or contiguous ranges over the kernels' threads for long
    tensors); ``sin_cos`` returns (sin, cos)."""
    function, op = _state["functions"][dtype], _ELEMENTARY[dtype][name]

    def apply(x: torch.Tensor):
        x = x.contiguous()
        count = x.numel()
        out = torch.empty((2,) + tuple(x.shape) if name == "sin_cos" else x.shape, dtype=dtype)
        if name == "sin_cos" or count < _ELEMENTARY_SPLIT:
            function(op, count, x.data_ptr(), out.data_ptr())
        else:  # contiguous ranges over the kernels' threads: each value is its own, whatever the split
            size = x.element_size()

            def run(first: int, last: int) -> None:
                start, stop = count * first // pieces, count * last // pieces
                function(op, stop - start, x.data_ptr() + size * start, out.data_ptr() + size * start)
            pieces = max(1, min(torch.get_num_threads(), count // _ELEMENTARY_SPLIT + 1))
            _in_threads(run, pieces)
        return (out[0], out[1]) if name == "sin_cos" else out
    return apply


def _elementary_numpy(name: str):
    """``f(a)`` for a contiguous float64 numpy array through the compiled float64 loop (``sin`` and
    ``cos`` through ``sin_cos``), in the calling thread, without a torch operation."""
    import numpy as np

    function = _state["functions"][torch.float64]
    op = _ELEMENTARY[torch.float64]["sin_cos" if name in ("sin", "cos") else name]
    part = {"sin": 0, "cos": 1}.get(name)

    def apply(a):
        out = np.empty((2,) + a.shape if part is not None else a.shape, np.float64)
        function(op, a.size, a.ctypes.data, out.ctypes.data)
        return out[part] if part is not None else out
    return apply


#: Elements from which a compiled elementary loop is split over the threads.
_ELEMENTARY_SPLIT = 16384


def elementary_match_torch() -> bool:
    """The compiled elementary loops against :mod:`fr_torch.core.exact_math`'s written-out functions
    on random and special float32 and float64 values: True when every value has the same bits (NaN
    as NaN)."""
    from fr_torch.core import exact_math
    generator = torch.Generator().manual_seed(66)
    for dtype in _ELEMENTARY:
        u = torch.rand(2048, generator=generator, dtype=torch.float64)
        specials = torch.tensor([0.0, -0.0, 1.0, -1.0, 1e-40, -1e-40, 1e-310, 3e38, -3e38, 1e300, math.inf, -math.inf,
                                 math.nan, 88.7, -87.4, 709.9, -708.5, 0.41421354, 2.4142137, 1e-30, 1e30],
                                dtype=torch.float64)
        angles = torch.cat([(u - 0.5) * 40, (u - 0.5) * 4e6, specials])
        arguments = {"atan": torch.cat([(u - 0.5) * 20, exact_math.exp((u - 0.5) * 40), specials]),
                     "exp": torch.cat([(u - 0.5) * 1500, (u - 0.5) * 180, specials]),
                     "log": torch.cat([exact_math.exp((u - 0.5) * 1400), exact_math.exp((u - 0.5) * 170), specials]),
                     "sqrt": torch.cat([exact_math.exp((u - 0.5) * 1400), exact_math.exp((u - 0.5) * 170), specials]),
                     "sin_cos": angles, "tan": angles}
        for name in _ELEMENTARY[dtype]:
            x = arguments[name].to(dtype)
            got, expected = _elementary(name, dtype)(x), exact_math.WRITTEN_OUT[name](x)
            pairs = zip(got, expected) if name == "sin_cos" else [(got, expected)]
            if not all(torch.equal(_bits(a), _bits(b)) for a, b in pairs):
                return False
    return True


def _bits(x: torch.Tensor) -> torch.Tensor:
    """A tensor's bits, every NaN as one (a NaN's sign and payload carry nothing)."""
    return torch.where(torch.isnan(x), math.nan, x).view(torch.int32 if x.dtype == torch.float32 else torch.int64)


def register_check(check, name: str = "kernels") -> None:
    """The test every process runs before trusting a kernel: ``check()`` -> True when it gives the
    torch path's bits.  ``"kernels"``: the scores and the gradient
    (:func:`fr_torch.core.likelihood.mixture.kernels_match_torch`, registered when that module
    loads; without it no kernel is used); ``"refine"``: the refinement loop
    (:func:`fr_torch.core.search.refine.refine_kernel_matches_torch`); ``"refine_lens"``: the same
    loop with the division model's k (the same check, registered by :mod:`fr_torch.core.search.lens`)."""
    _checks[name] = check


def available(name: str = "kernels") -> bool:
    """True when the fused kernels are built, loaded and checked in this process, and ``name``'s
    check (:func:`register_check`) passed; the first call does that (module docstring).
    ``FR_NATIVE=0`` turns every kernel off."""
    if os.environ.get("FR_NATIVE", "1") == "0" or "kernels" not in _checks or name not in _checks:
        return False
    verdicts = _state.setdefault("verdicts", {})
    if name not in verdicts:
        with _lock:
            if name not in verdicts:
                _trust(name, verdicts)
    return verdicts[name]


def _trust(name: str, verdicts: dict) -> None:
    """Load the kernels (once) and run ``name``'s check, recording the verdict (or take it from
    this machine's earlier run of the same check, :func:`_verdict_file`)."""
    if name != "kernels" and not available("kernels"):
        verdicts[name] = False
        return
    try:
        if "functions" not in _state:
            _state["functions"] = _load()
            _register_elementary()  # each loop is used only where it gives exact_math's bits
        verdicts[name] = True  # the check runs the kernel through the usual calls
        verdicts[name] = _checked(name, _checks[name])
        if not verdicts[name]:
            warnings.warn(f"fR: the fused CPU kernel ({name}) does not reproduce the torch path here; "
                          "running without it", RuntimeWarning, stacklevel=3)
    except Exception as exc:  # no compiler, a failed build: the torch path
        verdicts[name] = False
        _state["error"] = f"{type(exc).__name__}: {exc}"


def _verdict_file() -> Path:
    """Where this machine keeps the checks' verdicts for the loaded library: the file's name holds
    a hash of everything a verdict follows from -- the library (its name: source, flags, compiler,
    torch's version), the torch path (every source file of :mod:`fr_torch.core`), the CPU (its
    model and flags) and the settings that pick other library code (``ATEN_CPU_CAPABILITY``, MKL's,
    numpy's and OpenBLAS's).  Another version of any of these finds no file and checks again."""
    core = Path(__file__).resolve().parents[1]
    digest = hashlib.sha256(_state["library"].name.encode())
    for path in sorted(core.rglob("*.py")):
        digest.update(path.relative_to(core).as_posix().encode() + path.read_bytes())
    try:
        with open("/proc/cpuinfo") as info:
            first = info.read().split("\n\n")[0]
        digest.update("\n".join(line for line in first.splitlines()
                                if line.split(":")[0].strip() in ("vendor_id", "cpu family", "model", "model name",
                                                                  "flags")).encode())
    except OSError:
        digest.update(platform.processor().encode() + platform.machine().encode())
    for variable in _CPU_SETTINGS:
        digest.update(f"{variable}={os.environ.get(variable, '')}".encode())
    return _state["library"].with_name(f"verdicts-{digest.hexdigest()[:16]}.json")


#: Environment variables that pick other code in torch, MKL, numpy or OpenBLAS (:func:`_verdict_file`).
_CPU_SETTINGS = ("ATEN_CPU_CAPABILITY", "MKL_CBWR", "MKL_ENABLE_INSTRUCTIONS", "NPY_DISABLE_CPU_FEATURES",
                 "OPENBLAS_CORETYPE")


def _checked(name: str, check) -> bool:
    """``check()``'s verdict for ``name``: this machine's recorded one when there is one
    (:func:`_verdict_file`: the same check of the same code on the same CPU gives the same bits), else
    the check's, then recorded (written atomically; a file that cannot be read or written only
    means the check runs again)."""
    try:
        path = _state.get("verdict_file")
        if path is None:
            path = _state["verdict_file"] = _verdict_file()
        recorded = json.loads(path.read_text()) if path.is_file() else {}
    except (OSError, ValueError):
        path, recorded = None, {}
    if isinstance(recorded, dict) and isinstance(recorded.get(name), bool):
        return recorded[name]
    verdict = bool(check())
    if path is not None:
        recorded = {**(recorded if isinstance(recorded, dict) else {}), name: verdict}
        temporary = None
        try:
            with tempfile.NamedTemporaryFile("w", dir=path.parent, suffix=".tmp", delete=False) as out:
                temporary = out.name
                json.dump(recorded, out)
            os.replace(temporary, path)
        except OSError:
            if temporary is not None:
                Path(temporary).unlink(missing_ok=True)
    return verdict


def _register_elementary() -> None:
    """Hand the compiled loops (float32 and float64 tensors, float64 numpy arrays) to
    :mod:`fr_torch.core.exact_math` when they give its bits."""
    from fr_torch.core import exact_math
    if _checked("elementary", elementary_match_torch):
        exact_math.register_compiled({(name, dtype): _elementary(name, dtype)
                                      for dtype, names in _ELEMENTARY.items() for name in names})
        exact_math.register_compiled({(name, "numpy"): _elementary_numpy(name) for name in
                                      ("atan", "exp", "log", "sqrt", "tan", "sin", "cos")})
    else:
        warnings.warn("fR: the compiled elementary functions do not reproduce fr_torch.core.exact_math here; "
                      "running without them", RuntimeWarning, stacklevel=4)


def _pool() -> ThreadPoolExecutor:
    """The kernels' worker threads (one per core at most, started on demand)."""
    pool = _state.get("pool")
    if pool is None or _state.get("pool_pid") != os.getpid():  # a forked child has none of its parent's threads
        pool = _state["pool"] = ThreadPoolExecutor(max_workers=max(1, os.cpu_count() or 1),
                                                   thread_name_prefix="fr-native")
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
    function = _state["functions"]["scores"]
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
    tile = _tile_width(batch, hyp, vertical_block)
    tiles = -(-hyp // tile)
    items = batch * tiles

    def run(first: int, last: int) -> None:
        function(first, last, tiles, tile, n_seg, hyp, vertical_block, vertical_axis,
                 line_along.data_ptr(), factor.data_ptr(), scale.data_ptr(), flat.data_ptr(), coef.data_ptr(),
                 background, floor, out.data_ptr())

    _in_threads(run, items)
    return out


def _tile_width(batch: int, hyp: int, block: int) -> int:
    """Hypotheses per work item of :func:`measure_b_scores`: at most :data:`TILE`, whole runs of
    ``block`` (the vertical VP's), and with fewer images than threads small enough that each
    image's tiles keep every thread busy with about equal shares.  A hypothesis' score does not
    depend on its tile."""
    widest = TILE - TILE % block
    threads = max(1, torch.get_num_threads())
    if batch >= threads:
        return widest
    per_image = -(-threads // batch)  # tiles each image needs for every thread to have one
    runs = -(-hyp // block)
    tiles = max(per_image, -(-hyp // widest))
    tiles = -(-tiles // per_image) * per_image  # a multiple of the threads' share: equal loads
    return min(widest, max(block, -(-runs // tiles) * block))


def _in_threads(run, items: int) -> None:
    """``run(first, last)`` over ``items`` work items, split into contiguous ranges over
    ``torch.get_num_threads()`` of the kernels' threads (:func:`_pool`; ctypes calls release the
    GIL), one range even for one thread."""
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
    function = _state["functions"]["grad"]
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
                    grad_out.data_ptr(), objective.data_ptr(), grad.data_ptr()):
            raise MemoryError("fr_measure_b_grad: out of memory")

    _in_threads(run, batch)
    return objective, grad


def measure_b_refine(u: torch.Tensor, line_along: torch.Tensor, weight: torch.Tensor,
                     neg_inv_scale: torch.Tensor, log_coef: torch.Tensor, background: float, floor: float,
                     vertical_axis: int, grad_out: torch.Tensor, principal_point: torch.Tensor, lower: torch.Tensor,
                     span: torch.Tensor, prior: torch.Tensor | None, prior_centre: float, prior_flat: float,
                     steps: torch.Tensor, betas: tuple[float, float], eps: float, grad_bound: float,
                     periodic_pan: bool, lens: tuple | None = None) -> None:
    """fR's refinement loop in one call (:func:`fr_torch.core.search.refine.refine_fused`, bit for
    bit the torch loop's steps); call only when ``available("refine")`` (``available("refine_lens")``
    with ``lens``).

    ``u`` (B, H, P) float32 contiguous, stepped in place: the hypotheses in box units [pan, pitch,
    roll, log f] (P = 4) or [pan, pitch, roll, log f, k] (P = 5, with ``lens``); ``lower`` / ``span``
    (B, P) float32 the box in log f; ``grad_out`` (B,) float32, ``principal_point`` (B, 2) pixels;
    ``prior`` (B, 2) float32 [the focal prior's curvature weight, long side (pixels)] or None;
    ``steps`` (iterations, 2) float32 Adam's ``sqrt(1 - beta2^t)`` and ``lr_t / (1 - beta1^t)``;
    the segments (``line_along`` (B, 2N, 3), ``weight`` (B, N)) and constants as for
    :func:`measure_b_grad`.

    ``lens``: the division model (:class:`fr_torch.core.search.lens.SegmentGeometry`), a triple
    (offset (B, 2N, 2) float32 the endpoints' offsets from the distortion centre, which is
    ``principal_point``; rho (B, 2N) float32 their squared distance in units of the normalising radius;
    k_slope (B,) float32 the prior on k's ``-gamma W``, or None without that prior): every hypothesis
    is scored on the segments undistorted with its own k, ``line_along`` is not read.  The images are
    split over the threads as in :func:`measure_b_grad`.
    """
    function, work_floats = _state["functions"]["refine"], _state["functions"]["refine_work"]
    batch, n_seg = weight.shape
    hyp, params, iterations = u.shape[1], u.shape[2], steps.shape[0]
    line_along, weight = line_along.contiguous(), weight.contiguous()
    coef = torch.stack([neg_inv_scale.reshape(3), log_coef.reshape(3)], 1).to(torch.float32).contiguous()
    grad_out, principal_point, lower, span, steps = (x.to(torch.float32).contiguous() for x in
                                                     (grad_out.reshape(batch), principal_point, lower, span, steps))
    prior = None if prior is None else prior.to(torch.float32).contiguous()
    offset = rho = k_slope = None
    if lens is not None:
        offset, rho, k_slope = (None if x is None else x.to(torch.float32).contiguous() for x in lens)
    beta1, beta2 = betas
    work_size = int(work_floats(n_seg, hyp, params))

    def pointer(x: torch.Tensor | None) -> int:
        return 0 if x is None else x.data_ptr()

    def run(first: int, last: int) -> None:
        work = torch.empty(work_size, dtype=torch.float32)
        function(first, last, n_seg, hyp, vertical_axis, iterations,
                 line_along.data_ptr(), weight.data_ptr(), coef.data_ptr(), background, floor,
                 grad_out.data_ptr(), principal_point.data_ptr(), lower.data_ptr(), span.data_ptr(),
                 pointer(prior), prior_centre, prior_flat, steps.data_ptr(),
                 beta1, 1.0 - beta1, beta2, 1.0 - beta2, eps, grad_bound, int(periodic_pan),
                 pointer(offset), pointer(rho), pointer(k_slope), work.data_ptr(), u.data_ptr())

    _in_threads(run, batch)
