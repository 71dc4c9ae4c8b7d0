"""fr_torch.core.exact_math and exact's small linear algebra: accurate, IEEE at the edges, and the same
bits whatever oneMKL branch, torch kernel set or numpy SIMD level runs them."""
import hashlib
import json
import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from fr_torch.core import exact, exact_math
from tests.conftest import EMULATED_CPUS, REPO, checkout_env

FUNCTIONS = ("exp", "log", "atan", "sqrt", "sin", "cos", "tan", "asin", "acos", "asinh")


def _inputs(name: str, dtype: torch.dtype, count: int = 200_000) -> torch.Tensor:
    """Arguments spanning each function's domain, made with exact operations only."""
    u = torch.rand(count, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    if name in ("log", "sqrt"):
        x = exact_math.exp(u * 160.0 - 80.0)
    elif name in ("asin", "acos"):
        x = u * 2.0 - 1.0
    elif name == "exp":
        x = u * 170.0 - 85.0
    elif name == "tan":
        x = u * 3.0 - 1.5
    else:
        x = u * 40.0 - 20.0
    return x.to(dtype)


def _ulps(value: torch.Tensor, reference: np.ndarray, dtype: torch.dtype) -> float:
    reference = reference.astype(np.float64)
    spacing = np.spacing(np.abs(reference).astype(np.float32 if dtype == torch.float32 else np.float64))
    error = np.abs(value.double().numpy() - reference) / spacing.astype(np.float64)
    return float(error[np.isfinite(error)].max())


@pytest.mark.parametrize("dtype,limit", [(torch.float32, 4.0), (torch.float64, 3.5)])
@pytest.mark.parametrize("name", FUNCTIONS)
def test_each_function_is_within_a_few_units_in_the_last_place(name, dtype, limit):
    """Against float64 (for float32) or numpy's long double (for float64) references."""
    x = _inputs(name, dtype)
    value = getattr(exact_math, name)(x)
    reference_name = {"asin": "arcsin", "acos": "arccos", "atan": "arctan", "asinh": "arcsinh"}.get(name, name)
    wide = x.numpy().astype(np.float64 if dtype == torch.float32 else np.longdouble)
    reference = getattr(np, reference_name)(wide)
    assert _ulps(value, reference, dtype) <= limit


def test_sqrt_is_correctly_rounded():
    x = _inputs("sqrt", torch.float32)
    assert torch.equal(exact_math.sqrt(x), torch.sqrt(x.double()).float())  # rounding twice is exact for sqrt
    wide = _inputs("sqrt", torch.float64)
    root = exact_math.sqrt(wide).numpy()
    exact_root = np.sqrt(wide.numpy().astype(np.longdouble))
    assert np.all(np.abs(root - exact_root) <= np.spacing(root) / 2 * (1 + 1e-6))


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_special_values_follow_ieee(dtype):
    nan, inf = math.nan, math.inf
    x = torch.tensor([0.0, -0.0, 1.0, -1.0, inf, -inf, nan], dtype=dtype)

    assert exact_math.exp(x)[[0, 1, 4, 5]].tolist() == [1.0, 1.0, inf, 0.0] and torch.isnan(exact_math.exp(x)[6])
    assert exact_math.log(x)[[0, 1, 2, 4]].tolist() == [-inf, -inf, 0.0, inf]
    assert torch.isnan(exact_math.log(x)[[3, 5, 6]]).all()
    assert exact_math.atan(x)[[0, 4, 5]].tolist() == pytest.approx([0.0, math.pi / 2, -math.pi / 2])
    assert exact_math.sqrt(x)[[0, 2, 4]].tolist() == [0.0, 1.0, inf] and torch.isnan(exact_math.sqrt(x)[[3, 5, 6]]).all()
    assert torch.isnan(exact_math.sin(x)[4:]).all() and torch.isnan(exact_math.cos(x)[4:]).all()
    tiny = torch.tensor([1e-40 if dtype == torch.float32 else 1e-310], dtype=dtype)  # subnormal
    assert exact_math.log(tiny).item() == pytest.approx(math.log(tiny.item()), rel=1e-6)
    assert exact_math.exp(torch.tensor([-200.0 if dtype == torch.float32 else -1000.0, 1e4], dtype=dtype)).tolist() == [0.0, inf]
    assert exact_math.sin(torch.tensor([1e30], dtype=dtype)).abs().item() <= 1.0  # far arguments stay finite


def test_gradients_are_the_derivatives():
    x = torch.tensor([0.3, 0.7, 1.5], dtype=torch.float64, requires_grad=True)
    for name, derivative in [("exp", torch.exp), ("log", lambda v: 1 / v), ("atan", lambda v: 1 / (1 + v * v)),
                             ("sqrt", lambda v: 0.5 / torch.sqrt(v)), ("sin", torch.cos), ("cos", lambda v: -torch.sin(v))]:
        (grad,) = torch.autograd.grad(getattr(exact_math, name)(x).sum(), x)
        assert torch.allclose(grad, derivative(x.detach()), rtol=1e-12), name


_HASHES_CODE = """
import hashlib, json, numpy as np, torch
from fr_torch.core import exact, exact_math
from tests.test_exact_math import FUNCTIONS, _inputs
out = {}
for dtype in (torch.float32, torch.float64):
    for name in FUNCTIONS:
        out[name + str(dtype)] = hashlib.sha256(getattr(exact_math, name)(_inputs(name, dtype, 50_000)).numpy().tobytes()).hexdigest()
x = _inputs('log', torch.float64, 1000).numpy()
out['on_array'] = hashlib.sha256(exact_math.on_array(exact_math.tan, x).tobytes()).hexdigest()
a = torch.randn(64, 5, 5, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
out['solve'] = hashlib.sha256(exact.small_inverse(a)[0].numpy().tobytes()).hexdigest()
print(json.dumps(out))
"""


def test_the_same_bits_on_every_mkl_branch_kernel_set_and_numpy_level():
    """Fresh processes with oneMKL pinned to its COMPATIBLE and AVX2 branches (what other CPUs run),
    torch's default kernel set and numpy without AVX-512: every function's bits equal this process's
    (torch's own exp / log / atan / sqrt differ between these on 0.1-17 % of inputs)."""
    here = subprocess.run([sys.executable, "-c", _HASHES_CODE], cwd=REPO, env=checkout_env(), capture_output=True,
                          text=True, check=True).stdout
    reference = json.loads(here.strip().splitlines()[-1])
    for kernels, libraries in EMULATED_CPUS.items():
        extra = dict(libraries) if kernels == "torch-path" else {**libraries, "ATEN_CPU_CAPABILITY": kernels}
        done = subprocess.run([sys.executable, "-c", _HASHES_CODE], cwd=REPO, env=checkout_env(**extra),
                              capture_output=True, text=True)
        assert done.returncode == 0, done.stderr[-2000:]
        assert json.loads(done.stdout.strip().splitlines()[-1]) == reference, extra


def test_small_solve_inverse_and_definiteness():
    generator = torch.Generator().manual_seed(0)
    a = torch.randn(40, 4, 4, generator=generator, dtype=torch.float64)
    b = torch.randn(40, 4, 2, generator=generator, dtype=torch.float64)
    x, ok = exact.small_solve(a, b)
    assert ok.all() and torch.allclose(x, torch.linalg.solve(a, b), atol=1e-10)
    inverse, ok = exact.small_inverse(a)
    assert ok.all() and torch.allclose(inverse, torch.linalg.inv(a), atol=1e-10)
    assert not exact.small_solve(torch.zeros(1, 3, 3, dtype=torch.float64), torch.ones(1, 3, 1, dtype=torch.float64))[1].any()
    spd = a @ a.transpose(-1, -2) + 1e-3 * torch.eye(4, dtype=torch.float64)
    assert exact.positive_definite(spd).all() and not exact.positive_definite(-spd).any()
    symmetric = a + a.transpose(-1, -2)
    assert torch.equal(exact.positive_definite(symmetric), torch.linalg.eigvalsh(symmetric)[:, 0] > 0)
    # a batch of one gives the same bits as the batch
    assert torch.equal(exact.small_inverse(a[3:4])[0][0], inverse[3])
