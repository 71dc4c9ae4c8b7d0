"""Export the official CTRL-C checkpoint to the ONNX file that the ``ctrlc`` baseline runs.

**This script cannot be run in this repository's environment**: it needs a clone of the CTRL-C
code (https://github.com/jwlee-vcl/CTRL-C, with its own dependencies such as torchvision and
yacs) and the authors' trained checkpoint, neither of which is shipped here.  It imports the
user's CTRL-C model code from the path given with ``--ctrlc-repo``.  It has not been executed
against the real model or checkpoint by us: the wrapper, export and ``--check`` functions were
only exercised with a stand-in module having CTRL-C's ``forward(samples, extra_samples)``
signature, and the adapter side is tested with a small network exported by
``tests/test_baselines.py``.

Usage::

    python -m baselines.export_ctrlc_onnx --ctrlc-repo ~/src/CTRL-C \\
        --checkpoint ~/src/CTRL-C/logs/checkpoint.pth --out ctrlc.onnx
    export FR_CTRLC_ONNX=$PWD/ctrlc.onnx      # then: fr eval --methods ctrlc ...

The exported graph follows the contract of :mod:`baselines.ctrlc`: inputs ``image``
[1, 3, 512, 512], ``lines`` [1, 512, 3], ``line_mask`` [1, 512, 1] (all float32); outputs
``pred_zvp`` [1, 3], ``pred_fovy`` [1, 1] (radians), ``pred_hl`` [1, 3].  The wrapper feeds the
image as an un-padded NestedTensor (all-False mask) and the lines as CTRL-C's ``extra_samples``
dict, and drops the line-classification logits.  With ``--check`` the ONNX outputs are compared to
the PyTorch model's on random inputs.  If the dynamo exporter fails on the user's torch version,
``--legacy`` uses the TorchScript-based exporter instead.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch
from torch import nn

INPUT_NAMES = ["image", "lines", "line_mask"]
OUTPUT_NAMES = ["pred_zvp", "pred_fovy", "pred_hl"]


class CTRLCWrapper(nn.Module):
    """(image, lines, line_mask) -> (pred_zvp, pred_fovy, pred_hl) around CTRL-C's model."""

    def __init__(self, model: nn.Module, nested_tensor_cls):
        super().__init__()
        self.model = model
        self.nested_tensor_cls = nested_tensor_cls

    def forward(self, image: torch.Tensor, lines: torch.Tensor, line_mask: torch.Tensor):
        pad_mask = torch.zeros(image.shape[0], image.shape[2], image.shape[3], dtype=torch.bool,
                               device=image.device)
        samples = self.nested_tensor_cls(image, pad_mask)
        outputs = self.model(samples, {"lines": lines, "line_mask": line_mask})
        if isinstance(outputs, tuple):  # CTRL-C returns (outputs, extra_info)
            outputs = outputs[0]
        return outputs["pred_zvp"], outputs["pred_fovy"], outputs["pred_hl"]


def load_ctrlc(repo: Path, config: Path, checkpoint: Path) -> tuple[nn.Module, type]:
    """Build CTRL-C from the user's clone and load the checkpoint (CPU, eval mode)."""
    sys.path.insert(0, str(repo))
    try:
        from config import cfg  # CTRL-C's yacs config  (user code)
        from models import build_model  # (user code)
        from util.misc import NestedTensor  # (user code)
    except ImportError as exc:
        raise SystemExit(f"cannot import CTRL-C from {repo}: {exc}") from None
    cfg.merge_from_file(str(config))
    cfg.merge_from_list(["DEVICE", "cpu"])
    built = build_model(cfg)
    model = built[0] if isinstance(built, tuple) else built
    state = torch.load(str(checkpoint), map_location="cpu", weights_only=False)
    model.load_state_dict(state["model"] if isinstance(state, dict) and "model" in state else state)
    return model.eval(), NestedTensor


def example_inputs(num_lines: int = 512, size: int = 512, seed: int = 0) -> tuple[torch.Tensor, ...]:
    gen = torch.Generator().manual_seed(seed)
    image = torch.randn(1, 3, size, size, generator=gen)
    lines = torch.nn.functional.normalize(torch.randn(1, num_lines, 3, generator=gen), dim=-1)
    line_mask = torch.ones(1, num_lines, 1)
    return image, lines, line_mask


def export(wrapper: nn.Module, out: Path, legacy: bool = False, opset: int = 18) -> None:
    wrapper = wrapper.eval()
    args = example_inputs()
    with torch.no_grad():
        torch.onnx.export(wrapper, args, str(out), input_names=INPUT_NAMES, output_names=OUTPUT_NAMES,
                          opset_version=opset, dynamo=not legacy)


def check(wrapper: nn.Module, out: Path, tolerance: float = 1e-3) -> float:
    """Largest absolute difference between the ONNX and PyTorch outputs on random inputs."""
    import onnxruntime as ort

    args = example_inputs(seed=1)
    with torch.no_grad():
        expected = [t.numpy() for t in wrapper(*args)]
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    got = session.run(OUTPUT_NAMES, {n: a.numpy() for n, a in zip(INPUT_NAMES, args)})
    worst = max(float(abs(e - g).max()) for e, g in zip(expected, got))
    if worst > tolerance:
        raise SystemExit(f"ONNX and PyTorch outputs differ by {worst:.3g} (> {tolerance})")
    return worst


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ctrlc-repo", type=Path, required=True, help="clone of jwlee-vcl/CTRL-C")
    parser.add_argument("--checkpoint", type=Path, required=True, help="CTRL-C checkpoint (.pth)")
    parser.add_argument("--config", type=Path, default=None,
                        help="CTRL-C config (default: <repo>/config-files/ctrl-c.yaml)")
    parser.add_argument("--out", type=Path, default=Path("ctrlc.onnx"))
    parser.add_argument("--opset", type=int, default=18)
    parser.add_argument("--legacy", action="store_true", help="use the TorchScript-based exporter")
    parser.add_argument("--check", action="store_true", help="compare ONNX and PyTorch outputs")
    args = parser.parse_args(argv)
    config = args.config or args.ctrlc_repo / "config-files" / "ctrl-c.yaml"
    model, nested = load_ctrlc(args.ctrlc_repo, config, args.checkpoint)
    wrapper = CTRLCWrapper(model, nested)
    export(wrapper, args.out, legacy=args.legacy, opset=args.opset)
    print(f"wrote {args.out}")
    if args.check:
        print(f"max |onnx - torch| = {check(wrapper, args.out):.3g}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
