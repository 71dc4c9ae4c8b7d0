"""``ctrlc``: CTRL-C (Lee et al., ICCV 2021) run through onnxruntime with user-supplied weights.

J. Lee, H. Go, H. Lee, S. Cho, M. Sung, J. Kim, "CTRL-C: Camera calibration TRansformer with
Line-Classification", ICCV 2021.  The network itself is not re-implemented: the user exports the
official checkpoint to ONNX with ``fr export-ctrlc`` (:mod:`fr_baselines.export_ctrlc_onnx`) and points this adapter at
the file (constructor argument ``onnx_path`` or environment variable ``FR_CTRLC_ONNX``).  Without
weights the method is listed but ``available`` is False and every estimate is a flagged failure
with an "n/a (not supplied: ...)" reason (:func:`fr_torch.registry.not_supplied`).

ONNX contract (what the export script produces)
-----------------------------------------------
Inputs
  ``image``      [B, 3, 512, 512] float32: the whole image resized to 512 x 512 (bilinear, no
                 crop), RGB, scaled to [0, 1] and normalised with the ImageNet mean / std.
  ``lines``      [B, 512, 3] float32: segments longer than 10 px (``meta.segments`` when
                 given, else LSD as CTRL-C's loader runs it, :func:`ctrlc_segments`), endpoints normalised as ``2 / min(w, h) * (x - centre)`` with the centre
                 at (w / 2, h / 2), converted to unit homogeneous lines (cross product of the
                 homogeneous endpoints, normalised); when there are more than 512 segments, 512
                 are drawn with replacement with probability proportional to length (fixed seed,
                 so results are reproducible), otherwise all are used and the rest zero-padded.
                 This is CTRL-C's loader (``datasets/image_dataset.py`` at a7d4e7d: whole image
                 resized, no crop; centre (w/2, h/2); rho = 2/min(w, h); ImageNet normalisation),
                 except that its sampling is unseeded.
  ``line_mask``  [B, 512, 1] float32: 1 for real lines, 0 for padding.
Outputs
  ``pred_zvp``   [B, 3]: zenith VP, homogeneous, in the same normalised image coordinates.
  ``pred_fovy``  [B, 1]: field of view in radians across the normalising side ``min(w, h)``.
  ``pred_hl``    [B, 3]: horizon line in normalised coordinates (kept in ``extra``).

Conversion to our conventions
-----------------------------
CTRL-C normalises image coordinates by ``min(w, h) / 2`` (unit = half the short side), so its
focal length is ``f_n = 1 / tan(fovy / 2)`` in those units and ``f = (min(w, h) / 2) /
tan(fovy / 2)`` pixels.  (For the landscape images of the benchmarks min(w, h) = h, so fovy is
the vertical field of view.)  The vertical direction in the camera frame (x right, y down,
z forward) is ``(x_z, y_z, f_n w_z)`` for ``pred_zvp = (x_z, y_z, w_z)``; its sign is not
predicted, so we take the one pointing *up* (negative camera-y component), which is world-up
without needing ground truth.  Roll, tilt and pitch follow from it with the project's horizon
definitions (:func:`fr_torch.core.geometry.conventions.horizon_angles`).  CTRL-C estimates no pan, so ``rotation``
and ``pan_deg`` are None (an upright-consistent rotation with pan 0 is in
``extra["rotation_pan0"]``); roll / tilt are reported directly.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np
import torch

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import hfov_from_focal, horizon_angles
from fr_torch.errors import FRInputError
from fr_torch.images.convert import to_bgr8
from fr_torch.plugins.interface import CameraEstimate, ImageMeta, TimedCalibrator
from fr_torch.registry import not_supplied

from . import vp_geometry as vg
from .provenance import sha256

ALLOW_RANDOM_ENV = "FR_CTRLC_ALLOW_RANDOM"  # =1: run a --random-weights export (tests only)
INPUT_SIZE = 512
NUM_LINES = 512
MIN_LINE_LENGTH = 10.0
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], dtype=np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], dtype=np.float32)


def preprocess_image(image: np.ndarray, size: int = INPUT_SIZE) -> np.ndarray:
    """[1, 3, size, size] float32 network input from an image (BGR / grey, any :func:`to_bgr8` type)."""
    bgr = to_bgr8(image)
    rgb = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    resized = cv2.resize(rgb, (size, size), interpolation=cv2.INTER_LINEAR)
    x = (resized.astype(np.float32) / 255.0 - IMAGENET_MEAN) / IMAGENET_STD
    return np.ascontiguousarray(x.transpose(2, 0, 1)[None])


def ctrlc_segments(image: np.ndarray) -> np.ndarray:
    """Segments (N, 4) pixels detected as CTRL-C's own data loader does (``datasets/image_dataset.py``
    at a7d4e7d): LSD with ``scale=0.5`` (pylsd; OpenCV's LSD is the same algorithm, standard
    refinement) on ``cv2.cvtColor(rgb, COLOR_BGR2GRAY)`` -- the loader converts its RGB array with
    the BGR formula, which we keep so the network sees the lines it was trained with."""
    rgb = cv2.cvtColor(to_bgr8(image), cv2.COLOR_BGR2RGB)
    gray = cv2.cvtColor(rgb, cv2.COLOR_BGR2GRAY)
    lines = cv2.createLineSegmentDetector(cv2.LSD_REFINE_STD, 0.5).detect(gray)[0]
    return np.zeros((0, 4)) if lines is None else lines.reshape(-1, 4).astype(np.float64)


def preprocess_lines(segments: np.ndarray, width: int, height: int, num_lines: int = NUM_LINES,
                     min_length: float = MIN_LINE_LENGTH, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(lines [1, num_lines, 3], line_mask [1, num_lines, 1]) float32 from pixel segments (N, 4)."""
    segments = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    segments = segments[vg.segment_lengths(segments) > min_length]
    lines = np.zeros((num_lines, 3), np.float32)
    mask = np.zeros((num_lines, 1), np.float32)
    if len(segments) >= num_lines:  # as CTRL-C: sample whenever there are enough
        lengths = vg.segment_lengths(segments)
        rng = np.random.default_rng(seed)
        segments = segments[rng.choice(len(segments), num_lines, replace=True, p=lengths / lengths.sum())]
    count = len(segments)
    if count:
        centre = (width / 2.0, height / 2.0)  # CTRL-C's loader's centre (its input normalisation), not image_centre
        lines[:count] = vg.homogeneous_lines(segments, centre=centre, scale=2.0 / min(width, height))
        mask[:count] = 1.0
    return lines[None], mask[None]


def camera_from_ctrlc(zvp: np.ndarray, fovy_rad: float, width: int, height: int,
                      focal_px: float | None = None) -> dict:
    """focal / hfov / roll / tilt / pitch and an up direction from CTRL-C's normalised outputs.

    ``focal_px``: a known focal length (pixels), used instead of the predicted ``fovy`` (the
    known-focal evaluation gives every method the same focal; the angles depend on it)."""
    if focal_px is not None and focal_px > 0:
        focal = float(focal_px)
        focal_n = focal / (min(width, height) / 2.0)
    else:
        fovy_rad = float(np.clip(fovy_rad, 1e-4, math.pi - 1e-4))
        focal_n = 1.0 / math.tan(fovy_rad / 2.0)
        focal = (min(width, height) / 2.0) * focal_n
    zvp = np.asarray(zvp, dtype=np.float64).reshape(3)
    direction = np.array([zvp[0], zvp[1], focal_n * zvp[2]])
    norm = np.linalg.norm(direction)
    if not np.isfinite(norm) or norm < 1e-12:
        raise ValueError("degenerate zenith prediction")
    up = direction / norm
    if up[1] > 0:  # the vertical pointing up has a negative y component (camera y is down)
        up = -up
    # Our R has the downward vertical in column 1; horizon_angles only needs that column.
    down = -up
    r = np.zeros((3, 3))
    r[:, 1] = down
    angles = horizon_angles(torch.as_tensor(r))
    out = {k: float(v) for k, v in angles.items()}
    out.update(focal_px=focal, hfov_deg=float(hfov_from_focal(focal, width)), up=up)
    return out


class CTRLC(TimedCalibrator):
    """CTRL-C through onnxruntime (weights exported by the user; see the module docstring)."""

    def __init__(self, onnx_path: str | os.PathLike | None = None, providers=None, seed: int = 0,
                 num_lines: int = NUM_LINES, min_line_length: float = MIN_LINE_LENGTH, name: str = "ctrlc",
                 env_var: str = "FR_CTRLC_ONNX"):
        self.name = name
        self.env_var = env_var
        path = onnx_path if onnx_path is not None else os.environ.get(env_var) or None
        self.onnx_path = Path(path) if path else None
        self.providers = providers
        self.seed = int(seed)
        self.num_lines = int(num_lines)
        self.min_line_length = float(min_line_length)
        self._session = None

    @property
    def weights(self) -> str | None:
        """Which weights produce this row, for table captions: ONNX file name + sha256, and the
        checkpoint recorded by ``fr export-ctrlc`` in the file's metadata (None without weights)."""
        if not self.available:
            return None
        meta = self.metadata()
        text = f"{self.onnx_path.name} (sha256 {sha256(self.onnx_path)})"
        if meta.get("random_weights") == "true":
            return text + ", RANDOM WEIGHTS: a test of the export path, not a result"
        if meta.get("ctrlc_checkpoint"):
            text += f", exported from {meta['ctrlc_checkpoint']} (sha256 {meta.get('ctrlc_checkpoint_sha256', '?')})"
        return text

    def metadata(self) -> dict[str, str]:
        """The ONNX file's metadata (what ``fr export-ctrlc`` recorded; empty for other exports)."""
        return dict(self.session().get_modelmeta().custom_metadata_map)

    @property
    def available(self) -> bool:
        """True when an ONNX file was supplied and exists."""
        return self.onnx_path is not None and self.onnx_path.is_file()

    def session(self):
        if self._session is None:
            import onnxruntime as ort  # optional dependency, only needed with weights

            providers = self.providers or ["CPUExecutionProvider"]
            self._session = ort.InferenceSession(str(self.onnx_path), providers=providers)
        return self._session

    def input_shape(self) -> tuple[int, int]:
        """(image side S, number of lines L) the ONNX file takes (512, 512 for CTRL-C's config);
        ``num_lines`` given to the constructor wins when the file has a dynamic line axis."""
        shapes = {i.name: i.shape for i in self.session().get_inputs()}
        size = shapes.get("image", [None] * 4)[2]
        lines = shapes.get("lines", [None] * 3)[1]
        return (size if isinstance(size, int) else INPUT_SIZE,
                lines if isinstance(lines, int) else self.num_lines)

    def run(self, image_in: np.ndarray, lines: np.ndarray, line_mask: np.ndarray) -> dict[str, np.ndarray]:
        """Raw network outputs for preprocessed inputs (see the module docstring)."""
        sess = self.session()
        feeds = {"image": image_in, "lines": lines, "line_mask": line_mask}
        names = [i.name for i in sess.get_inputs()]
        missing = [k for k in feeds if k not in names]
        if missing:
            raise RuntimeError(f"{self.onnx_path}: ONNX inputs are {names}, expected image, lines, line_mask")
        outputs = sess.run(["pred_zvp", "pred_fovy", "pred_hl"], {k: feeds[k] for k in names})
        return dict(zip(["pred_zvp", "pred_fovy", "pred_hl"], outputs))

    def _estimate(self, image, meta: ImageMeta) -> CameraEstimate:
        if not self.available:
            reason = not_supplied(f"weights: set {self.env_var}" if self.onnx_path is None
                                  else f"weights: {self.onnx_path} not found")
            return CameraEstimate.failure(self.name, reason)
        if self.metadata().get("random_weights") == "true" and os.environ.get(ALLOW_RANDOM_ENV) != "1":
            # an export-path test file: its numbers must never end up in a table by mistake
            return CameraEstimate.failure(self.name, not_supplied(
                f"{self.onnx_path.name} has random weights (export test); set {ALLOW_RANDOM_ENV}=1 to run it anyway"))
        if image is None:
            return CameraEstimate.failure(self.name, "bad input: CTRL-C needs the image")
        try:
            width, height = vg.image_size(image, meta)
            segments = (vg.input_segments(image, meta) if meta.segments is not None
                        else ctrlc_segments(image))
        except FRInputError as exc:
            return CameraEstimate.failure(self.name, f"bad input: {exc}")
        if width <= 0 or height <= 0:
            return CameraEstimate.failure(self.name, "unknown image size")
        pp = meta.principal_point
        if pp is not None and max(abs(pp[0] - (width - 1) / 2), abs(pp[1] - (height - 1) / 2)) > 1.0:
            # the network's frame is the whole resized image: its principal point is the centre
            return CameraEstimate.failure(self.name, "unsupported: CTRL-C assumes the principal point at "
                                                     "the image centre (evaluate with --pp centre)")
        size, num_lines = self.input_shape()
        image_in = preprocess_image(image, size)
        lines, mask = preprocess_lines(segments, width, height, num_lines, self.min_line_length, self.seed)
        if mask.sum() < 1:
            return CameraEstimate.failure(self.name, "no line segments longer than "
                                                     f"{self.min_line_length:g} px")
        out = self.run(image_in, lines, mask)
        zvp, fovy, hl = out["pred_zvp"][0], float(out["pred_fovy"][0].reshape(-1)[0]), out["pred_hl"][0]
        if not (np.isfinite(zvp).all() and math.isfinite(fovy)):
            return CameraEstimate.failure(self.name, "non-finite network output")
        try:
            cam = camera_from_ctrlc(zvp, fovy, width, height, focal_px=meta.focal_px)
        except ValueError as exc:
            return CameraEstimate.failure(self.name, str(exc))
        # CTRL-C predicts the horizon (gravity), not the heading: a pan-unknown camera (R with pan 0)
        camera = Camera.from_angles(width, height, cam["focal_px"], roll_deg=cam["roll_deg"],
                                    pitch_deg=cam["pitch_deg"])
        return CameraEstimate(
            method=self.name, camera=camera,
            extra={"pred_zvp": zvp.tolist(), "pred_fovy_rad": fovy, "pred_hl": np.asarray(hl).tolist(),
                   "up": cam["up"].tolist(), "rotation_pan0": camera.rotation},
        )



def make_ctrlc_retrained(onnx_path: str | os.PathLike | None = None, providers=None, seed: int = 0,
                         num_lines: int = NUM_LINES, min_line_length: float = MIN_LINE_LENGTH) -> CTRLC:
    """The paper reports CTRL-C with two trainings: the published checkpoint (``ctrlc``,
    ``$FR_CTRLC_ONNX``) and a second training; this row takes the second checkpoint, exported the
    same way, from ``onnx_path`` or ``$FR_CTRLC_RETRAINED_ONNX``."""
    return CTRLC(onnx_path, providers=providers, seed=seed, num_lines=num_lines, min_line_length=min_line_length,
                 name="ctrlc-retrained", env_var="FR_CTRLC_RETRAINED_ONNX")
