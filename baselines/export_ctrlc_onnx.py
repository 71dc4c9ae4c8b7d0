"""``fr export-ctrlc``: build the real CTRL-C network from the user's CTRL-C checkout, load a
checkpoint, export it to the ONNX file the ``ctrlc`` baseline runs, and check ONNX against PyTorch.

CTRL-C (Lee et al., ICCV 2021, https://github.com/jwlee-vcl/CTRL-C, Apache-2.0) is not copied
into this project: its model code is imported from the checkout given with ``--ctrlc-source``
(default ``$FR_CTRLC_SOURCE``), built with its own yacs config (``config-files/ctrl-c.yaml`` unless
``--config``; ``--opts KEY VALUE ...`` overrides entries as CTRL-C's own scripts do), on the CPU,
with the backbone's ImageNet download switched off (the checkpoint holds all weights)::

    fr export-ctrlc --checkpoint gsv.pth --out ctrlc.onnx --check-image some.jpg
    fr eval --dataset yud --methods ctrlc --ctrlc-onnx ctrlc.onnx

Needs the ``ctrlc`` extra (``pip install 'fr-torch[ctrlc]'``: torchvision for CTRL-C's ResNet
backbone, yacs for its config, onnx / onnxscript for the exporter).  PyPI's torchvision wheels are
linked against CUDA torch; with a CPU-only torch their compiled operators (``nms``, ``roi_align``
...) fail to load and ``import torchvision`` stops while registering their fake kernels.  CTRL-C
uses none of them (only the pure-Python ResNet and ``IntermediateLayerGetter``), so in that case
the import is retried without those registrations (see :func:`import_torchvision`).

``--random-weights`` builds the network with random weights instead of a checkpoint: **for tests
of the export path only** -- such a model's numbers are meaningless.  The file records it in its
metadata (``random_weights=true``) and ``fr eval`` says so in the caption of the row.

The exported graph follows the contract of :mod:`fr_baselines.ctrlc`: inputs ``image`` [1, 3, S, S]
(S = ``DATASETS.INPUT_WIDTH``, 512), ``lines`` [1, L, 3], ``line_mask`` [1, L, 1] (L =
``DATASETS.NUM_INPUT_LINES``, 512), all float32; outputs ``pred_zvp`` [1, 3], ``pred_fovy`` [1, 1]
(radians), ``pred_hl`` [1, 3].  The wrapper feeds the image as CTRL-C's un-padded NestedTensor and
the lines as its ``extra_samples`` dict and drops the line-classification logits.  The check runs
both on the same preprocessed real image (the adapter's own preprocessing) and fails when any
output differs by more than ``--tolerance`` (default 1e-4).  The ONNX metadata records the
checkpoint's file name and sha256, the config and the CTRL-C source (see :func:`provenance`).
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import sys
import types
import warnings
from pathlib import Path

import numpy as np

from .provenance import sha256

INPUT_NAMES = ["image", "lines", "line_mask"]
OUTPUT_NAMES = ["pred_zvp", "pred_fovy", "pred_hl"]
SOURCE_ENV = "FR_CTRLC_SOURCE"
EXTRA_HINT = "install the ctrlc extra: pip install 'fr-torch[ctrlc]' (torchvision, yacs, onnx, onnxscript)"


class ExportError(ValueError):
    """A user-facing export problem (one line, no traceback)."""


def import_torchvision():
    """``import torchvision``; with a CPU-only torch and a CUDA-linked torchvision wheel, retry
    without ``torchvision._meta_registrations`` (fake kernels of compiled ops CTRL-C does not use)."""
    try:
        import torchvision
        return torchvision
    except ModuleNotFoundError:
        raise ExportError(f"CTRL-C needs torchvision: {EXTRA_HINT}") from None
    except (RuntimeError, OSError) as exc:  # "operator torchvision::nms does not exist"
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]
        sys.modules["torchvision._meta_registrations"] = types.ModuleType("torchvision._meta_registrations")
        try:
            import torchvision
        except Exception as exc2:  # noqa: BLE001
            raise ExportError(f"torchvision does not import with this torch ({exc}; {exc2})") from None
        print(f"note: torchvision's compiled operators are unavailable ({exc}); CTRL-C does not use them",
              file=sys.stderr)
        return torchvision


def import_ctrlc(source: Path):
    """CTRL-C's ``(cfg, build_model, NestedTensor, backbone module)`` imported from ``source``."""
    if not (source / "models" / "ctrlc.py").is_file() or not (source / "config" / "defaults.py").is_file():
        raise ExportError(f"{source} is not a CTRL-C checkout (no models/ctrlc.py, config/defaults.py); "
                          f"clone https://github.com/jwlee-vcl/CTRL-C and pass --ctrlc-source or set {SOURCE_ENV}")
    import_torchvision()
    try:
        import yacs  # noqa: F401
    except ModuleNotFoundError:
        raise ExportError(f"CTRL-C's config needs yacs: {EXTRA_HINT}") from None
    # CTRL-C's top-level packages have generic names (config, models, util): import them from the
    # checkout, not from anything else on sys.path.
    for name in [m for m in sys.modules if m.split(".")[0] in ("config", "models", "util")]:
        del sys.modules[name]
    sys.path.insert(0, str(source))
    sys.dont_write_bytecode, old = True, sys.dont_write_bytecode
    try:
        config = importlib.import_module("config")
        models = importlib.import_module("models")
        backbone = importlib.import_module("models.backbone")
        misc = importlib.import_module("util.misc")
    finally:
        sys.path.remove(str(source))
        sys.dont_write_bytecode = old
    if not Path(models.__file__).resolve().is_relative_to(source.resolve()):
        raise ExportError(f"imported 'models' from {models.__file__}, not from {source}")
    return config.cfg, models.build_model, misc.NestedTensor, backbone


def build_ctrlc(source: Path, config: Path | None = None, opts: list[str] | None = None):
    """CTRL-C's network (eval mode, CPU, random weights) and the config it was built with."""
    import torch

    cfg0, build_model, nested_tensor, backbone = import_ctrlc(source)
    cfg = cfg0.clone()
    cfg.merge_from_file(str(config or source / "config-files" / "ctrl-c.yaml"))
    cfg.merge_from_list(list(opts or []) + ["DEVICE", "cpu"])
    backbone.is_main_process = lambda: False  # pretrained=is_main_process(): no ImageNet download
    built = build_model(cfg)
    model = built[0] if isinstance(built, tuple) else built
    return model.to(torch.device("cpu")).eval(), nested_tensor, cfg


def load_checkpoint(model, checkpoint: Path) -> None:
    """Load CTRL-C's checkpoint (``{"model": state_dict, ...}`` or a bare state dict), strictly."""
    import torch

    try:
        state = torch.load(str(checkpoint), map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 - older checkpoints pickle argparse / yacs objects
        state = torch.load(str(checkpoint), map_location="cpu", weights_only=False)
    state = state["model"] if isinstance(state, dict) and "model" in state else state
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).splitlines()[0:3]
        raise ExportError(f"{checkpoint} does not fit this CTRL-C config: {' '.join(first)}") from None


def make_wrapper(model, nested_tensor_cls):
    """(image, lines, line_mask) -> (pred_zvp, pred_fovy, pred_hl) around CTRL-C's model."""
    import torch
    from torch import nn

    class CTRLCWrapper(nn.Module):
        def __init__(self):
            super().__init__()
            self.model = model

        def forward(self, image: torch.Tensor, lines: torch.Tensor, line_mask: torch.Tensor):
            pad_mask = torch.zeros(image.shape[0], image.shape[2], image.shape[3], dtype=torch.bool,
                                   device=image.device)
            outputs = self.model(nested_tensor_cls(image, pad_mask), {"lines": lines, "line_mask": line_mask})
            if isinstance(outputs, tuple):  # CTRL-C returns (outputs, extra_info)
                outputs = outputs[0]
            return outputs["pred_zvp"], outputs["pred_fovy"], outputs["pred_hl"]

    return CTRLCWrapper().eval()


def real_inputs(image: np.ndarray, size: int, num_lines: int, min_line_length: float):
    """The adapter's own preprocessing of one image (see :mod:`fr_baselines.ctrlc`)."""
    from .ctrlc import ctrlc_segments, preprocess_image, preprocess_lines  # torch, cv2: only when exporting

    height, width = image.shape[:2]
    lines, mask = preprocess_lines(ctrlc_segments(image), width, height, num_lines, min_line_length)
    return preprocess_image(image, size), lines, mask


def export(wrapper, inputs, out: Path, dynamo: bool = False, opset: int = 18) -> None:
    """Trace ``wrapper`` on ``inputs`` into ``out``.  The default TorchScript tracer records the branch
    CTRL-C's attention takes (``torch.equal(query, key)``), which depends only on the layer (self-
    vs cross-attention), not on the data, so the graph is exact for every input."""
    import torch

    args = tuple(torch.from_numpy(a) for a in inputs)
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # TracerWarnings about CTRL-C's shape asserts
        torch.onnx.export(wrapper, args, str(out), input_names=INPUT_NAMES, output_names=OUTPUT_NAMES,
                          opset_version=opset, dynamo=dynamo, external_data=False)


def compare(wrapper, out: Path, inputs) -> float:
    """Largest absolute difference between the ONNX (onnxruntime, CPU) and PyTorch outputs."""
    import onnxruntime as ort
    import torch

    with torch.no_grad():
        expected = [t.numpy() for t in wrapper(*(torch.from_numpy(a) for a in inputs))]
    session = ort.InferenceSession(str(out), providers=["CPUExecutionProvider"])
    got = session.run(OUTPUT_NAMES, dict(zip(INPUT_NAMES, inputs)))
    for e, g in zip(expected, got):
        if e.shape != g.shape or not np.isfinite(g).all():
            raise ExportError(f"ONNX output shape {g.shape} / finite {np.isfinite(g).all()} vs PyTorch {e.shape}")
    return max(float(np.abs(e - g).max()) for e, g in zip(expected, got))


def provenance(source: Path, checkpoint: Path | None, cfg, opts: list[str], max_diff: float) -> dict[str, str]:
    """What produced the file: written into the ONNX metadata (strings) and read by the adapter."""
    commit = ""
    head = source / ".git" / "HEAD"
    if head.is_file():  # a git clone: the commit it is at
        ref = head.read_text().strip()
        ref_file = source / ".git" / ref[5:] if ref.startswith("ref: ") else None
        commit = ref_file.read_text().strip() if ref_file and ref_file.is_file() else ref
    elif (source / "PROVENANCE.md").is_file():
        commit = "see PROVENANCE.md"
    return {
        "ctrlc_checkpoint": checkpoint.name if checkpoint else "",
        "ctrlc_checkpoint_sha256": sha256(checkpoint) if checkpoint else "",
        "random_weights": "false" if checkpoint else "true",
        "ctrlc_source": str(source),
        "ctrlc_source_commit": commit,
        "ctrlc_config": json.dumps({"BACKBONE": cfg.MODELS.BACKBONE, "TRANSFORMER": dict(cfg.MODELS.TRANSFORMER),
                                    "INPUT": [cfg.DATASETS.INPUT_WIDTH, cfg.DATASETS.INPUT_HEIGHT],
                                    "NUM_INPUT_LINES": cfg.DATASETS.NUM_INPUT_LINES,
                                    "MIN_LINE_LENGTH": cfg.DATASETS.MIN_LINE_LENGTH, "opts": opts}),
        "onnx_vs_torch_max_abs_diff": f"{max_diff:.3g}",
    }


def write_metadata(path: Path, props: dict[str, str]) -> None:
    import onnx

    model = onnx.load(str(path))
    onnx.helper.set_model_props(model, props)
    onnx.save(model, str(path))


# The ``fr export-ctrlc`` command: (module, one-line help), declared in pyproject.toml's
# ``fr_torch.commands`` entry-point group.
COMMAND = ("fr_baselines.export_ctrlc_onnx", "export the real CTRL-C network (your checkout + checkpoint) to ONNX")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    weights = parser.add_mutually_exclusive_group(required=True)
    weights.add_argument("--checkpoint", type=Path, help="CTRL-C checkpoint (.pth) from the authors or your training")
    weights.add_argument("--random-weights", action="store_true",
                         help="random weights instead of a checkpoint: TESTS OF THE EXPORT ONLY, never results")
    parser.add_argument("--out", type=Path, default=Path("ctrlc.onnx"), help="ONNX file to write (default ctrlc.onnx)")
    parser.add_argument("--ctrlc-source", type=Path, default=None,
                        help=f"CTRL-C checkout (git clone of jwlee-vcl/CTRL-C; default ${SOURCE_ENV})")
    parser.add_argument("--config", type=Path, default=None, help="CTRL-C yacs config (default config-files/ctrl-c.yaml)")
    parser.add_argument("--opts", nargs="+", default=[], metavar="KEY VALUE",
                        help="config overrides, as CTRL-C's scripts take them (e.g. MODELS.BACKBONE resnet18)")
    parser.add_argument("--check-image", type=Path, default=None,
                        help="image for the ONNX-vs-PyTorch check (default: a synthetic room)")
    parser.add_argument("--tolerance", type=float, default=1e-4, help="largest allowed |ONNX - PyTorch| (default 1e-4)")
    parser.add_argument("--seed", type=int, default=0, help="torch seed for --random-weights")
    parser.add_argument("--opset", type=int, default=18)
    parser.add_argument("--dynamo", action="store_true",
                        help="torch.export-based exporter (fails on CTRL-C's data-dependent attention "
                             "branches in torch 2.13; default: the TorchScript-based tracer)")


def run(args: argparse.Namespace) -> int:
    import torch

    from fr_torch.images.io import load_image
    from fr_torch.synthetic import render_manhattan_room

    source = args.ctrlc_source or (Path(os.environ[SOURCE_ENV]) if os.environ.get(SOURCE_ENV) else None)
    if source is None:
        raise ExportError(f"where is CTRL-C? pass --ctrlc-source PATH or set {SOURCE_ENV} "
                          "(git clone https://github.com/jwlee-vcl/CTRL-C)")
    if args.checkpoint is not None and not args.checkpoint.is_file():
        raise FileNotFoundError(f"checkpoint {args.checkpoint} not found")
    torch.manual_seed(args.seed)
    model, nested, cfg = build_ctrlc(source.expanduser(), args.config, args.opts)
    if args.checkpoint is not None:
        load_checkpoint(model, args.checkpoint)
    else:
        print("WARNING: random weights -- for testing the export only; its numbers mean nothing", file=sys.stderr)
    if cfg.DATASETS.INPUT_WIDTH != cfg.DATASETS.INPUT_HEIGHT:
        raise ExportError("the ctrlc adapter feeds square images (INPUT_WIDTH == INPUT_HEIGHT)")
    image = load_image(args.check_image) if args.check_image else render_manhattan_room(500.0)
    inputs = real_inputs(image, cfg.DATASETS.INPUT_WIDTH, cfg.DATASETS.NUM_INPUT_LINES,
                         float(cfg.DATASETS.MIN_LINE_LENGTH))
    wrapper = make_wrapper(model, nested)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    export(wrapper, inputs, args.out, dynamo=args.dynamo, opset=args.opset)
    diff = compare(wrapper, args.out, inputs)
    if not diff <= args.tolerance:
        raise ExportError(f"ONNX and PyTorch outputs differ by {diff:.3g} (> {args.tolerance:g}) on "
                          f"{args.check_image or 'the synthetic check image'}")
    write_metadata(args.out, provenance(source, args.checkpoint, cfg, args.opts, diff))
    print(f"wrote {args.out} (sha256 {sha256(args.out)[:12]}...; max |ONNX - PyTorch| = {diff:.3g} on "
          f"{args.check_image or 'a synthetic room'})")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="fr export-ctrlc", description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except (ExportError, FileNotFoundError) as exc:
        print(f"fr export-ctrlc: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
