"""Fusion of per-frame fR estimates into a current calibration (:class:`OnlineCalibrator`).

The maths only: frame sources, outputs and the ``fr track`` command live in :mod:`fr_torch.video.track`.
Manhattan-frame geometry (the 24 symmetries, nearest rotation, angles) is in :mod:`fr_torch.core.geometry.conventions`.

Fusion (one *epoch* = the frames since the last restart)
--------------------------------------------------------
* A frame is **rejected** when the estimate failed or ``result.reliable`` is False (too few
  segments, non-Manhattan scene, or an error bound above its limit: the promise of
  ``configs/reliability.json``, :mod:`fr_torch.core.reliability.bounds`; the estimator's reliability
  stage sets both).
* Each accepted frame carries predicted absolute errors ``e`` (roll, tilt in deg, focal in %; a
  missing prediction counts as the thresholds).  Predicted *mean absolute* errors are turned into
  standard deviations ``s = e * sqrt(pi / 2)`` (Gaussian), floored at ``min_sigma``.
* **Rotation**: the frame's R is first mapped to the representative of its Manhattan frame that
  is closest to the fused R (the 24 proper signed permutations P of the columns, ``R P``; chordal
  distance), then fused by the weighted **chordal L2 mean on SO(3)**: ``M = sum_i w_i R_i`` and
  ``R = U diag(1, 1, det(U V^T)) V^T`` from the SVD ``M = U S V^T``, with
  ``w_i = 1 / (s_roll^2 + s_tilt^2)``.  Euler angles are never averaged.
* **Focal length**: weighted mean of ``ln f`` with ``w_i = 1 / s_focal^2`` (s as a fraction).
* Old frames are forgotten exponentially: all weights are multiplied by ``1 - 1/memory`` at each
  accepted frame, so the fused state follows a slowly drifting camera (``memory`` frames).
* The fused standard deviations are ``1 / sqrt(sum w)`` (independent errors assumed -- optimistic
  for errors that are correlated across frames of one scene), floored at ``min_sigma``.
* **Camera moved**: an accepted frame *disagrees* with the fused state when, for roll, tilt,
  focal (%) or the rotation angle after symmetry resolution, ``|difference| > change_k *
  sqrt(s_frame^2 + s_fused^2)``.  Disagreeing frames are held back (not fused); when ``patience``
  consecutive accepted frames disagree with the fused state but agree with each other, fusion
  restarts from them (``restarted`` is True on that frame, ``epoch`` increments).  A single
  disagreeing frame followed by an agreeing one is an outlier and is dropped.
"""
from __future__ import annotations

import copy
import math
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from fr_torch.core.geometry.camera import Camera, camera_record
from fr_torch.core.geometry.conventions import align_to, nearest_rotation, rotation_angle_deg, rotation_angles
from fr_torch.core.reliability.model import load_thresholds

SIGMA_FROM_MAE = math.sqrt(math.pi / 2.0)  # Gaussian: std = MAE * sqrt(pi / 2)


@camera_record
@dataclass
class FrameEstimate:
    """What the calibrator needs from one frame (built from a CalibrationResult).

    ``camera``: the frame's estimate (:class:`fr_torch.core.geometry.camera.Camera`, None when it failed);
    ``focal_px``, ``rotation``, ``roll_deg``, ``tilt_deg`` ... are read-only views of it.
    """

    index: int
    ok: bool
    reliable: bool
    camera: Camera | None = None
    predicted_error: dict[str, float] | None = None
    reason: str = ""


def camera_json(camera: Camera | None) -> dict[str, Any] | None:
    """A :class:`Camera` as JSON-ready values (None stays None); :func:`camera_from_json` reads it."""
    if camera is None:
        return None
    return {"width": camera.width, "height": camera.height, "focal_px": camera.focal_px,
            "principal_point": None if camera.principal_point is None else list(map(float, camera.principal_point)),
            "rotation": None if camera.rotation is None else np.asarray(camera.rotation).tolist(),
            "pan_known": camera.pan_known}


def camera_from_json(record: dict[str, Any] | None) -> Camera | None:
    """The :class:`Camera` of :func:`camera_json`'s output; ValueError when it holds no finite
    focal length and rotation (the only cameras the fusion keeps)."""
    if record is None:
        return None
    rotation = np.asarray(record["rotation"], np.float64).reshape(3, 3)
    focal = float(record["focal_px"])
    if not (math.isfinite(focal) and focal > 0 and np.isfinite(rotation).all()):
        raise ValueError("camera without a finite focal length and rotation")
    pp = record.get("principal_point")
    return Camera(int(record["width"]), int(record["height"]), focal, None if pp is None else tuple(map(float, pp)),
                  rotation, bool(record.get("pan_known", True)))


# FusedState.to_json: its keys, in order (``fr track``'s calibration.json)
STATE_JSON_KEYS = ("frame", "status", "epoch", "n_fused", "focal_px", "rotation", "roll_deg", "tilt_deg", "pitch_deg",
                   "pan_deg", "sigma", "restarted", "disagreement")


@camera_record
@dataclass
class FusedState:
    """Fused calibration after a frame.  ``status`` of that frame: ``fused``, ``started``,
    ``restarted``, ``rejected`` (unreliable), ``held`` (disagrees: possible camera move / outlier).

    ``camera``: the fused camera (image size and principal point of the fused frames, fused focal
    length and rotation; None before the first accepted frame); ``focal_px``, ``rotation``,
    ``roll_deg``, ``tilt_deg``, ``pitch_deg``, ``pan_deg``, ``hfov_deg`` are read-only views of it.
    """

    frame: int
    status: str
    epoch: int  # fusion epoch: increments at every (re)start
    n_fused: int = 0
    camera: Camera | None = None
    sigma: dict[str, float] | None = None  # fused standard deviations: roll_deg, tilt_deg, focal_pct
    restarted: bool = False
    disagreement: float | None = None  # largest normalised difference frame vs fused (units of change_k)

    @property
    def valid(self) -> bool:
        return self.focal_px is not None

    def to_json(self) -> dict[str, Any]:
        out = {key: copy.deepcopy(getattr(self, key)) for key in STATE_JSON_KEYS}
        if self.rotation is not None:
            out["rotation"] = np.asarray(self.rotation).tolist()
        return out


@dataclass
class OnlineCalibrator:
    """Fuses per-frame fR estimates into a current calibration; see the module docstring.

    ``history`` holds the fused states after the latest ``history_length`` frames (None: every
    frame), so memory stays bounded however long the stream runs.  :meth:`checkpoint` and
    :meth:`restore` carry the fusion over to another process (a resumed ``fr track``).
    """

    memory: float = 30.0
    change_k: float = 3.0
    patience: int = 2
    min_sigma: dict[str, float] = field(default_factory=lambda: {"roll_deg": 0.2, "tilt_deg": 0.2, "focal_pct": 1.0})
    default_error: dict[str, float] | None = None  # used when a frame has no predicted error (thresholds)
    history_length: int | None = 1000
    history: deque[FusedState] = field(init=False)

    def __post_init__(self) -> None:
        if self.default_error is None:

            self.default_error = load_thresholds()
        self.history = deque(maxlen=self.history_length)
        self.reset()
        self.epoch = -1

    # ------------------------------------------------------------------ state

    def reset(self) -> None:
        self._m = np.zeros((3, 3))  # sum of w_rot * aligned R
        self._w_rot = 0.0
        self._logf = 0.0  # sum of w_f * ln f
        self._w_f = 0.0
        self._w_roll = self._w_tilt = 0.0  # precisions for the reported sigmas
        self._n = 0
        self._pending: list[FrameEstimate] = []
        self.rotation: np.ndarray | None = None
        self.focal_px: float | None = None
        self._camera: Camera | None = None  # the last fused frame's camera: image size, principal point
        self._frame = -1

    def frame_sigmas(self, predicted_error: dict[str, float] | None) -> dict[str, float]:
        """A frame's standard deviations {roll_deg, tilt_deg (degrees), focal_pct (%)} from its
        predicted mean absolute errors (same keys and units): ``s = e * sqrt(pi / 2)`` floored at
        ``min_sigma``; a missing or non-finite prediction counts as ``default_error`` (the
        thresholds).  The frame's fusion weights are ``1 / s^2`` (module docstring)."""
        pred = dict(self.default_error)
        if predicted_error:
            pred.update({k: v for k, v in predicted_error.items() if v is not None and math.isfinite(v)})
        return {k: max(self.min_sigma[k], SIGMA_FROM_MAE * pred[k]) for k in ("roll_deg", "tilt_deg", "focal_pct")}

    def fused_sigma(self) -> dict[str, float] | None:
        if self._n == 0:
            return None
        return {"roll_deg": max(self.min_sigma["roll_deg"], 1 / math.sqrt(self._w_roll)),
                "tilt_deg": max(self.min_sigma["tilt_deg"], 1 / math.sqrt(self._w_tilt)),
                "focal_pct": max(self.min_sigma["focal_pct"], 100 / math.sqrt(self._w_f))}

    def _add(self, e: FrameEstimate) -> None:
        s = self.frame_sigmas(e.predicted_error)
        decay = 1.0 - 1.0 / self.memory if self._n else 0.0
        rotation = e.rotation if self.rotation is None else align_to(e.rotation, self.rotation)
        w_rot = 1.0 / (s["roll_deg"] ** 2 + s["tilt_deg"] ** 2)
        w_f = 1.0 / (s["focal_pct"] / 100.0) ** 2
        self._m = decay * self._m + w_rot * rotation
        self._w_rot = decay * self._w_rot + w_rot
        self._logf = decay * self._logf + w_f * math.log(e.focal_px)
        self._w_f = decay * self._w_f + w_f
        self._w_roll = decay * self._w_roll + 1.0 / s["roll_deg"] ** 2
        self._w_tilt = decay * self._w_tilt + 1.0 / s["tilt_deg"] ** 2
        self._n += 1
        self.rotation = nearest_rotation(self._m)
        self.focal_px = math.exp(self._logf / self._w_f)
        self._camera = e.camera

    def disagreement(self, e: FrameEstimate, rotation: np.ndarray, focal_px: float, sigma: dict | None) -> float:
        """Largest |difference| / sqrt(s_frame^2 + s_ref^2) over roll, tilt, focal and rotation angle."""
        s = self.frame_sigmas(e.predicted_error)
        ref = sigma or s
        aligned = align_to(e.rotation, rotation)
        angles = rotation_angles(rotation)
        mine = rotation_angles(aligned)  # the frame's angles in the reference's labelling of the axes
        roll, tilt = mine["roll_deg"], mine["tilt_deg"]
        z = [abs(roll - angles["roll_deg"]) / math.hypot(s["roll_deg"], ref["roll_deg"]),
             abs(tilt - angles["tilt_deg"]) / math.hypot(s["tilt_deg"], ref["tilt_deg"]),
             100 * abs(e.focal_px - focal_px) / focal_px / math.hypot(s["focal_pct"], ref["focal_pct"]),
             rotation_angle_deg(aligned, rotation) / math.hypot(math.hypot(s["roll_deg"], s["tilt_deg"]),
                                                                math.hypot(ref["roll_deg"], ref["tilt_deg"]))]
        return max(z)

    # ------------------------------------------------------------------ update

    @staticmethod
    def frame_from_result(result, index: int) -> FrameEstimate:
        ok = bool(getattr(result, "ok", False)) and getattr(result, "rotation", None) is not None
        return FrameEstimate(index=index, ok=ok, reliable=ok and bool(result.reliable),
                             camera=result.camera if ok else None,
                             predicted_error=result.predicted_error, reason=result.reason)

    def update(self, result, index: int | None = None) -> FusedState:
        """Feed one frame's CalibrationResult (annotated with predicted errors); returns the fused state."""
        self._frame = self._frame + 1 if index is None else int(index)
        e = result if isinstance(result, FrameEstimate) else self.frame_from_result(result, self._frame)
        restarted, z = False, None
        if not (e.ok and e.reliable):
            status = "rejected"
        elif self._n == 0:
            self.epoch += 1
            self._add(e)
            status = "started"
        else:
            z = self.disagreement(e, self.rotation, self.focal_px, self.fused_sigma()) / self.change_k
            if z <= 1.0:
                self._add(e)
                self._pending.clear()
                status = "fused"
            else:
                # keep only the held-back frames that agree with this one (consecutive run)
                sigma = self.frame_sigmas(e.predicted_error)
                self._pending = [p for p in self._pending
                                 if self.disagreement(p, e.rotation, e.focal_px, sigma) <= self.change_k]
                self._pending.append(e)
                status = "held"
                if len(self._pending) >= self.patience:
                    pending = self._pending
                    self.reset()
                    self.epoch += 1
                    for p in pending:
                        self._add(p)
                    status, restarted = "restarted", True
        state = self.state(status)
        state.restarted, state.disagreement = restarted, z
        self.history.append(state)
        return state

    # ------------------------------------------------------------------ checkpoint

    def checkpoint(self) -> dict[str, Any]:
        """The fusion's whole state as JSON-ready values (sums of weights and weighted values,
        epoch, last frame index, the held-back frames, the last fused frame's camera): feeding
        :meth:`restore` of a new calibrator with it continues the fusion exactly."""
        return {"epoch": self.epoch, "frame": self._frame, "n": self._n, "m": self._m.tolist(),
                "w_rot": self._w_rot, "logf": self._logf, "w_f": self._w_f, "w_roll": self._w_roll,
                "w_tilt": self._w_tilt, "camera": camera_json(self._camera),
                "pending": [{"index": p.index, "camera": camera_json(p.camera), "predicted_error": p.predicted_error}
                            for p in self._pending]}

    def restore(self, checkpoint: dict[str, Any]) -> None:
        """Continue from :meth:`checkpoint`'s output; ValueError (one line) when it is not one."""
        try:
            m = np.asarray(checkpoint["m"], np.float64).reshape(3, 3)
            numbers = [float(checkpoint[k]) for k in ("w_rot", "logf", "w_f", "w_roll", "w_tilt")]
            n, epoch, frame = int(checkpoint["n"]), int(checkpoint["epoch"]), int(checkpoint["frame"])
            camera = camera_from_json(checkpoint["camera"])
            pending = [FrameEstimate(index=int(p["index"]), ok=True, reliable=True, camera=camera_from_json(p["camera"]),
                                     predicted_error=p.get("predicted_error")) for p in checkpoint["pending"]]
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"not a fusion checkpoint ({type(exc).__name__}: {exc})") from None
        if not (np.isfinite(m).all() and all(math.isfinite(v) for v in numbers)) or n < 0 or (n and camera is None) \
                or (n and min(numbers[2:]) <= 0) or any(p.camera is None for p in pending):
            raise ValueError("not a fusion checkpoint (weights or cameras missing or not finite)")
        self.reset()
        self._m, (self._w_rot, self._logf, self._w_f, self._w_roll, self._w_tilt) = m, numbers
        self._n, self.epoch, self._frame, self._camera, self._pending = n, epoch, frame, camera, pending
        if n:
            self.rotation = nearest_rotation(self._m)
            self.focal_px = math.exp(self._logf / self._w_f)

    def state(self, status: str = "fused") -> FusedState:
        if self._n == 0:
            return FusedState(frame=self._frame, status=status, epoch=self.epoch)
        camera = replace(self._camera, focal_px=self.focal_px, rotation=self.rotation.copy(), pan_known=True)
        return FusedState(frame=self._frame, status=status, epoch=self.epoch, n_fused=self._n, camera=camera,
                          sigma=self.fused_sigma())
