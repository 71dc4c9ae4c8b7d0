"""Elementary functions whose bits do not depend on the CPU: ``exp``, ``log``, ``atan``, ``asin``,
``acos``, ``asinh``, ``sin``, ``cos``, ``tan`` and ``sqrt`` of float32 and float64 tensors (and of
Python numbers, :func:`of`, and numpy arrays, :func:`on_array`).

torch's CPU kernels take these functions from oneMKL's vector maths (VML), and MKL picks a code
branch per CPU family: the same input gives other last bits on another CPU.  Of 2,000,000 random
inputs, MKL's COMPATIBLE branch (the one it runs on CPUs it does not know) and its AVX-512 branch
differ on 1.6 % of float32 ``exp`` values, 4.4 % of ``atan``, 17 % of ``sqrt``, and on 0.1–4.5 % of
the float64 functions; a search that takes hundreds of steps from such values ends elsewhere in the
last bits, and sometimes in another basin.  numpy's ``log``, ``exp``, ``tan``, ``arctan`` and
``log1p`` likewise run other code on a CPU without AVX-512.

The functions here are built from operations IEEE 754 rounds the same way everywhere (``+``, ``-``,
``*``, ``/``, comparisons, rounding to an integer, bit moves), one rounding each, in a fixed order,
never fused: range reduction, a polynomial, the power of two written into the exponent bits.  The
same bits on any CPU, under every torch kernel set and every MKL branch (``tests/test_exact_math.py``
runs them in processes pinned to other branches).  ``fr_torch/core/likelihood/kernels_measure_b.c``
spells out the same operations in C, inside the fused kernels and as loops over whole tensors that
:mod:`fr_torch.core.likelihood.native` registers here (:func:`register_compiled`) once they have given
these functions' bits: one call instead of some thirty torch operations.

Accuracy (``tests/test_exact_math.py``, against float64 references for float32 and long double ones
for float64; maximum error in units in the last place): float32 ``exp`` 1.2, ``log`` 1.8, ``atan``
2.2, ``asin`` / ``acos`` / ``asinh`` 2.7-3.4, ``sin`` / ``cos`` / ``tan`` 0.5 (through float64);
float64 1-3; ``sqrt`` correctly rounded in both.  ``sin`` / ``cos`` / ``tan`` reduce their
argument exactly below 2^20 radians.  ``exp`` flushes results below the smallest normal number to 0.

On a GPU (any device but the CPU) each function is torch's own: CUDA's maths library gives the same
bits run after run on a device, and its functions do not dispatch by CPU.  Differentiable: each
function's gradient is the usual derivative, written with the same elementary operations.

Shapes: elementwise, any shape; float16 / bfloat16 inputs are left to torch.
"""
from __future__ import annotations

import math

import torch

_H = float.fromhex

# ---- float32: the constants kernels_measure_b.c writes as the same hexadecimal literals ----------
#: log2(e), and ln 2 in two parts: ``n * LN2_HI_32`` is exact for |n| < 2^8.
LOG2E_32 = _H("0x1.715476p+0")
LN2_HI_32 = _H("0x1.62e4p-1")
LN2_LO_32 = _H("0x1.7f7d1cp-20")
#: 1 / k! for k = 0..7 (Taylor's series of exp on [-ln2/2, ln2/2]).
EXP_32 = tuple(map(_H, ("0x1p+0", "0x1p+0", "0x1p-1", "0x1.555556p-3", "0x1.555556p-5", "0x1.111112p-7",
                        "0x1.6c16c2p-10", "0x1.a01a02p-13")))
#: 2 / (2k + 1) for k = 1..4: log(m) = 2s + s (sum_k c_k s^2k), s = (m - 1) / (m + 1).
LOG_32 = tuple(map(_H, ("0x1.555556p-1", "0x1.99999ap-2", "0x1.24924ap-2", "0x1.c71c72p-3")))
SQRT2_32 = _H("0x1.6a09e6p+0")
#: (atan(u) - u) / u^3 as a degree-4 polynomial in z = u^2, least squares on [0, tan^2(pi/8)].
ATAN_32 = tuple(map(_H, ("-0x1.555554p-2", "0x1.99973ep-3", "-0x1.2421a8p-3", "0x1.b82b1cp-4", "-0x1.089378p-4")))
TAN_PI_8_32 = _H("0x1.a8279ap-2")
TAN_3PI_8_32 = _H("0x1.3504f4p+1")
PI_4_32 = _H("0x1.921fb6p-1")
PI_2_32 = _H("0x1.921fb6p+0")

# ---- float64 --------------------------------------------------------------------------------------
LOG2E_64 = _H("0x1.71547652b82fep+0")
LN2_HI_64 = _H("0x1.62e42fefa38p-1")  # 42 bits: n * LN2_HI_64 exact for |n| < 2^11
LN2_LO_64 = _H("0x1.ef35793c7673p-45")
EXP_64 = tuple(1.0 / math.factorial(k) for k in range(14))  # Taylor to degree 13 on [-ln2/2, ln2/2]
LOG_64 = tuple(2.0 / (2 * k + 1) for k in range(1, 11))
SQRT2_64 = _H("0x1.6a09e667f3bcdp+0")
#: atan(j / 8), j = 0..8: atan(t) = atan(j/8) + atan((t - j/8) / (1 + t j/8)), |u| <= 1/16.
ATAN_EIGHTHS_64 = tuple(map(_H, (
    "0x0p+0", "0x1.fd5ba9aac2f6ep-4", "0x1.f5b75f92c80ddp-3", "0x1.6f61941e4def1p-2", "0x1.dac670561bb4fp-2",
    "0x1.1e00babdefeb4p-1", "0x1.4978fa3269ee1p-1", "0x1.700a7c5784634p-1", "0x1.921fb54442d18p-1")))
_ATAN_EIGHTHS_TABLE = torch.tensor(ATAN_EIGHTHS_64, dtype=torch.float64)  # CPU: the written-out path's only device
ATAN_64 = tuple((-1.0) ** k / (2 * k + 1) for k in range(1, 9))  # u^3 .. u^17
PI_2_64 = _H("0x1.921fb54442d18p+0")
TWO_OVER_PI_64 = _H("0x1.45f306dc9c883p-1")
#: pi/2 in three parts of 33, 33 and 53 bits: k * part exact for |k| < 2^20 (Cody and Waite).
PIO2_1 = _H("0x1.921fb544p+0")
PIO2_2 = _H("0x1.0b4611a6p-34")
PIO2_3 = _H("0x1.3198a2e037073p-69")
SIN_64 = tuple((-1.0) ** k / math.factorial(2 * k + 1) for k in range(1, 9))  # r^3 .. r^17
COS_64 = tuple((-1.0) ** k / math.factorial(2 * k) for k in range(2, 10))  # r^4 .. r^18
#: Veltkamp's splitter for float64: a = hi + lo with 26-bit halves, so that hi * hi etc. are exact.
SPLITTER_64 = 134217729.0


def _native(x: torch.Tensor) -> bool:
    return x.device.type != "cpu" or x.dtype not in (torch.float32, torch.float64)


#: Compiled loops of these same functions, by (name, dtype), name one of "atan", "exp", "log",
#: "sqrt", "sin_cos" and (float64) "tan", each ``f(x) -> y`` for a CPU tensor of that dtype, and by
#: (name, "numpy") for a float64 numpy array (:func:`on_array`; "sin" and "cos" too): registered by
#: :mod:`fr_torch.core.likelihood.native` once they have given this module's bits on its check
#: (:func:`register_compiled`).
_COMPILED: dict = {}


def register_compiled(functions: dict) -> None:
    """Use ``functions`` ((name, dtype) -> CPU loop) for CPU tensors from now on: they must give this
    module's bits (their registrant checks that); one call of a loop costs what one torch operation
    does, where the written-out function takes some thirty."""
    _COMPILED.update(functions)


def _compiled(name: str, x: torch.Tensor):
    """The registered loop for ``x``, or None (none for its dtype or device, or a gradient to track)."""
    if x.device.type != "cpu" or (name, x.dtype) not in _COMPILED:
        return None
    if torch.is_grad_enabled() and x.requires_grad:
        return None
    return _COMPILED[name, x.dtype]


def _horner(x: torch.Tensor, coefficients) -> torch.Tensor:
    """c0 + x (c1 + x (c2 + ...)), innermost first: one product and one sum per coefficient."""
    acc = torch.full_like(x, coefficients[-1])
    for c in reversed(coefficients[:-1]):
        acc = acc * x + c
    return acc


def power_of_two(n: torch.Tensor, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """2^n as ``dtype`` (float32 or float64) for integer-valued ``n`` (any dtype, same shape) within
    the normal range (-126..127, -1022..1023), written into the exponent bits: exact on any device."""
    if dtype == torch.float32:
        return torch.bitwise_left_shift(n.to(torch.int32) + 127, 23).view(torch.float32)
    return torch.bitwise_left_shift(n.to(torch.int64) + 1023, 52).view(torch.float64)


def _exp(x: torch.Tensor) -> torch.Tensor:
    single = x.dtype == torch.float32
    log2e, hi, lo = (LOG2E_32, LN2_HI_32, LN2_LO_32) if single else (LOG2E_64, LN2_HI_64, LN2_LO_64)
    low, high = (-126.0, 127.0) if single else (-1022.0, 1023.0)
    n = torch.round(x * log2e).clamp(low, high)
    r = (x - n * hi) - n * lo
    y = _horner(r, EXP_32 if single else EXP_64) * power_of_two(n, x.dtype)
    over, under = (88.72283935546875, -87.33654022216797) if single else (709.782712893384, -708.3964185322641)
    y = torch.where(x > over, math.inf, y)
    return torch.where(x < under, 0.0, y)


def _log(x: torch.Tensor) -> torch.Tensor:
    single = x.dtype == torch.float32
    ints, bits, bias, tiny = ((torch.int32, 23, 127, 2.0 ** -126) if single else (torch.int64, 52, 1023, 2.0 ** -1022))
    subnormal = x < tiny
    scaled = torch.where(subnormal, x * 2.0 ** bits, x).contiguous()
    word = scaled.view(ints)
    exponent = torch.bitwise_right_shift(word, bits) - bias - torch.where(subnormal, bits, 0)
    mantissa_mask = (1 << bits) - 1
    m = torch.bitwise_or(torch.bitwise_and(word, mantissa_mask), bias << bits).view(x.dtype)  # [1, 2)
    big = m > (SQRT2_32 if single else SQRT2_64)
    m = torch.where(big, m * 0.5, m)
    exponent = torch.where(big, exponent + 1, exponent)
    f = m - 1.0
    s = f / (f + 2.0)
    z = s * s
    log_m = s * 2.0 + s * (z * _horner(z, LOG_32 if single else LOG_64))
    e = exponent.to(x.dtype)
    hi, lo = (LN2_HI_32, LN2_LO_32) if single else (LN2_HI_64, LN2_LO_64)
    y = e * hi + (e * lo + log_m)
    y = torch.where(x == 0, -math.inf, y)
    y = torch.where(x == math.inf, math.inf, y)
    return torch.where((x < 0) | torch.isnan(x), math.nan, y)


def _atan(x: torch.Tensor) -> torch.Tensor:
    a = x.abs()
    if x.dtype == torch.float32:  # one quotient: u = a, (a - 1) / (a + 1) or -1 / a, |u| <= tan(pi/8)
        middle, far = a > TAN_PI_8_32, a > TAN_3PI_8_32
        num = torch.where(far, -1.0, torch.where(middle, a - 1.0, a))
        den = torch.where(far, a, torch.where(middle, a + 1.0, 1.0))
        u = num / den
        v = torch.where(u.abs() < 2.0 ** -30, 0.0, u)  # atan(u) = u there, and no subnormal square (slow)
        z = v * v
        r = u + u * (z * _horner(z, ATAN_32))
        r = torch.where(middle, r + PI_4_32, r)
        r = torch.where(far, r + PI_4_32, r)  # pi/2 - atan(1/a) = pi/4 + pi/4 + atan(-1/a)
        return torch.copysign(r, x)
    inverted = a > 1.0
    t = torch.where(inverted, 1.0 / a, a)  # [0, 1]
    j = torch.round(t * 8.0)
    c = j * 0.125
    u = (t - c) / (t * c + 1.0)  # |u| <= 1/16
    z = u * u
    r = u + u * (z * _horner(z, ATAN_64))
    r = _ATAN_EIGHTHS_TABLE[j.nan_to_num(0.0).to(torch.int64)] + r
    r = torch.where(inverted, PI_2_64 - r, r)
    return torch.copysign(r, x)


def _sin_cos64(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(sin x, cos x) of float64 ``x``: x = k pi/2 + r, |r| <= pi/4, Taylor's series in r.  Beyond
    |x| = 2^20 (where k pi/2 stops being exact in three parts) x is first taken modulo 2 pi (the
    same bits everywhere, with less accuracy)."""
    x = torch.where(x.abs() > 2.0 ** 20, torch.remainder(x, 2.0 * math.pi), x)
    k = torch.round(x * TWO_OVER_PI_64)
    r = ((x - k * PIO2_1) - k * PIO2_2) - k * PIO2_3
    z = r * r
    sin_r = r + r * (z * _horner(z, SIN_64))
    cos_r = 1.0 + z * (-0.5 + z * _horner(z, COS_64))
    quadrant = torch.remainder(k.nan_to_num(0.0, 0.0, 0.0).to(torch.int64), 4)
    swap = (quadrant == 1) | (quadrant == 3)
    sin_x = torch.where(swap, cos_r, sin_r)
    cos_x = torch.where(swap, sin_r, cos_r)
    sin_x = torch.where(quadrant >= 2, -sin_x, sin_x)
    cos_x = torch.where((quadrant == 1) | (quadrant == 2), -cos_x, cos_x)
    finite = torch.isfinite(x)
    return torch.where(finite, sin_x, math.nan), torch.where(finite, cos_x, math.nan)


def _sqrt64(x: torch.Tensor) -> torch.Tensor:
    """Correctly rounded float64 square root: torch's root (any estimate within an ulp), then moved
    to its neighbour wherever x lies beyond the square of the midpoint between them, a test made in
    integers.  With y = Y 2^k (Y a 53-bit integer) and y^2 = p + e exactly (Veltkamp's split and
    Dekker's product), every term of x - (y +- u/2)^2 is an integer multiple of 2^(2k-4) below
    2^60, so int64 arithmetic decides it exactly.  Twice, for an estimate off by two ulps."""
    tiny, huge = x < 2.0 ** -900, x > 2.0 ** 900  # scaled by 2^+-1000 (exact), the root by 2^-+500
    x = torch.where(tiny, x * 2.0 ** 1000, torch.where(huge, x * 2.0 ** -1000, x))
    y = torch.sqrt(x)
    regular = (x > 0) & (x < math.inf)
    for _ in range(2):
        y = torch.where(regular, y, 1.0)
        _, exponent = torch.frexp(y)
        k = exponent.to(torch.int64) - 53  # y = Y 2^k, 2^52 <= Y < 2^53
        c = y * SPLITTER_64
        hi = c - (c - y)
        lo = y - hi
        p = y * y
        e = ((hi * hi - p) + (hi * lo) * 2.0) + lo * lo  # y^2 - p, exactly
        unit = power_of_two(4 - 2 * k)  # terms in units of 2^(2k - 4)
        t = ((x - p) * unit).to(torch.int64)  # x - p: exact (Sterbenz), an integer in these units
        err = (e * unit).to(torch.int64)
        whole = (y * power_of_two(-k)).to(torch.int64)  # Y
        lowest = whole == (1 << 52)  # y a power of two: the spacing below is half the one above
        above = t - err - 16 * whole - 4 > 0  # x > (y + u/2)^2, u = 2^k
        below = t - err + torch.where(lowest, 8 * whole, 16 * whole) - torch.where(lowest, 1, 4) < 0
        y = torch.where(above, torch.nextafter(y, y.new_tensor(math.inf)),
                        torch.where(below, torch.nextafter(y, y.new_tensor(0.0)), y))
    root = torch.where(regular, y, torch.sqrt(x))  # 0, NaN and inf as torch's
    return torch.where(tiny, root * 2.0 ** -500, torch.where(huge, root * 2.0 ** 500, root))


class _Elementary(torch.autograd.Function):
    """value and gradient of one function: forward ``value(x)``, backward ``grad * slope(x, y)``."""

    @staticmethod
    def forward(ctx, x, value, slope):
        y = value(x)
        ctx.slope = slope
        ctx.save_for_backward(x, y)
        return y

    @staticmethod
    def backward(ctx, grad):
        x, y = ctx.saved_tensors
        return grad * ctx.slope(x, y), None, None


def _apply(x: torch.Tensor, value, slope) -> torch.Tensor:
    if torch.is_grad_enabled() and x.requires_grad:
        return _Elementary.apply(x, value, slope)
    return value(x)


def _evaluate(name: str, x: torch.Tensor, value, slope) -> torch.Tensor:
    """torch's ``name`` off the CPU, the registered compiled loop where there is one, else ``value``
    written out (with ``slope`` as its derivative)."""
    if _native(x):
        return getattr(torch, name)(x)
    compiled = _compiled(name, x)
    if compiled is not None:
        return compiled(x)
    return _apply(x, value, slope)


def exp(x: torch.Tensor) -> torch.Tensor:
    """e^x, elementwise; results below the smallest normal number are 0."""
    return _evaluate("exp", x, _exp, lambda x, y: y)


def log(x: torch.Tensor) -> torch.Tensor:
    """Natural logarithm, elementwise: -inf at 0, NaN below 0."""
    return _evaluate("log", x, _log, lambda x, y: 1.0 / x)


def atan(x: torch.Tensor) -> torch.Tensor:
    """Arctangent in [-pi/2, pi/2] radians, elementwise."""
    return _evaluate("atan", x, _atan, lambda x, y: 1.0 / (x * x + 1.0))


def sqrt(x: torch.Tensor) -> torch.Tensor:
    """Square root, correctly rounded (float32 through the float64 root: rounding twice is exact
    for a square root), elementwise; NaN below 0."""
    return _evaluate("sqrt", x, WRITTEN_OUT["sqrt"], lambda x, y: 0.5 / y)


def _sqrt32(x: torch.Tensor) -> torch.Tensor:
    """float32 root rounded from the correctly rounded float64 one (rounding twice is exact for a
    square root).  torch's own float64 root is not enough: oneMKL's AVX2 branch misses by more than
    an ulp, and the float32 rounding then differs."""
    return _sqrt64(x.to(torch.float64)).to(torch.float32)


def _sin_cos(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(sin x, cos x) in ``x``'s dtype, through float64 (a float32 result rounded once)."""
    s, c = _sin_cos64(x.to(torch.float64))
    return s.to(x.dtype), c.to(x.dtype)


def _tan(x: torch.Tensor) -> torch.Tensor:
    s, c = _sin_cos64(x.to(torch.float64))
    return (s / c).to(x.dtype)


#: The written-out functions by the names of the compiled loops that must reproduce them
#: (:func:`register_compiled`; ``fr_torch.core.likelihood.native.elementary_match_torch`` checks).
WRITTEN_OUT = {"atan": _atan, "exp": _exp, "log": _log, "sin_cos": _sin_cos, "tan": _tan,
               "sqrt": lambda x: _sqrt64(x) if x.dtype == torch.float64 else _sqrt32(x)}


def sin(x: torch.Tensor) -> torch.Tensor:
    """Sine of radians, elementwise (float32 through float64, rounded once)."""
    if _native(x):
        return torch.sin(x)
    if _compiled("sin_cos", x) is not None:
        return sin_cos(x)[0]
    return _apply(x, lambda v: _sin_cos(v)[0], lambda x, y: cos(x))


def cos(x: torch.Tensor) -> torch.Tensor:
    """Cosine of radians, elementwise (float32 through float64, rounded once)."""
    if _native(x):
        return torch.cos(x)
    if _compiled("sin_cos", x) is not None:
        return sin_cos(x)[1]
    return _apply(x, lambda v: _sin_cos(v)[1], lambda x, y: -sin(x))


def sin_cos(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(:func:`sin` x, :func:`cos` x) from one argument reduction: the same bits as the two calls."""
    if _native(x) or (torch.is_grad_enabled() and x.requires_grad):
        return sin(x), cos(x)
    compiled = _compiled("sin_cos", x)
    return compiled(x) if compiled is not None else _sin_cos(x)


def tan(x: torch.Tensor) -> torch.Tensor:
    """Tangent of radians, elementwise: sin / cos, each as above."""
    return _evaluate("tan", x, _tan, lambda x, y: y * y + 1.0)


def asin(x: torch.Tensor) -> torch.Tensor:
    """Arcsine in [-pi/2, pi/2] radians, elementwise: atan(x / sqrt((1 - x)(1 + x))); NaN beyond
    [-1, 1]."""
    if _native(x):
        return torch.asin(x)
    return _apply(x, lambda v: atan(v / sqrt((1.0 - v) * (1.0 + v))), lambda x, y: 1.0 / sqrt((1.0 - x) * (1.0 + x)))


def acos(x: torch.Tensor) -> torch.Tensor:
    """Arccosine in [0, pi] radians, elementwise: 2 atan(sqrt((1 - x) / (1 + x))); NaN beyond [-1, 1]."""
    if _native(x):
        return torch.acos(x)
    return atan(sqrt((1.0 - x) / (1.0 + x))) * 2.0


def asinh(x: torch.Tensor) -> torch.Tensor:
    """Inverse hyperbolic sine, elementwise: sign(x) log1p(a + a^2 / (1 + sqrt(1 + a^2))), a = |x|,
    with log1p(y) = log(u) - ((u - 1) - y) / u, u = 1 + y (Goldberg's correction); |x| below 1e150."""
    if _native(x):
        return torch.asinh(x)
    a = x.abs()
    y = a + (a * a) / (sqrt(a * a + 1.0) + 1.0)
    u = y + 1.0
    log1p = torch.where(u == 1.0, y, log(u) - ((u - 1.0) - y) / u)
    return torch.copysign(log1p, x)


def of(function, value: float) -> float:
    """``function`` (one of this module's) of a Python number, in float64: the C library's ``math``
    functions also pick their code by CPU (glibc's FMA variants)."""
    return float(on_array(function, value))


def on_array(function, a) -> "np.ndarray":
    """``function`` (one of this module's) of a number or numpy array, as a float64 numpy array of
    the same shape: numpy's own ``log``, ``tan``, ... run other code on other CPUs.  Through the
    registered compiled loop straight on the array where there is one (no torch operation: these
    run per photo), else through a tensor."""
    import numpy as np
    a = np.asarray(a, np.float64)
    flat = np.ascontiguousarray(a.reshape(-1))
    compiled = _COMPILED.get((function.__name__, "numpy"))
    values = compiled(flat) if compiled is not None else function(torch.from_numpy(flat)).numpy()
    return values.reshape(a.shape)
