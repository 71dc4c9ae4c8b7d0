""":class:`CalibrationResult`: one image's estimate and everything said about it -- the camera, the
lens, the segments' labels, the ranked vanishing points, the horizon, the cues, the predicted
errors and bounds, ``reliable`` and its reason -- with its JSON form (:data:`JSON_KEYS`, the CLI's
output schema) and its exports (OpenCV, COLMAP, kornia).
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from fr_torch.core.exports import colmap_camera, opencv_camera
from fr_torch.core.geometry.camera import Camera, camera_record
from fr_torch.core.geometry.conventions import VERTICAL_AXIS
from fr_torch.core.geometry.horizon import Horizon
from fr_torch.core.geometry.lens import distort_points, distortion_record, normalising_radius, undistort_points
from fr_torch.core.reliability.bounds import horizon_bound_pct

#: ``horizon_reason`` of a result that no horizon promise was applied to (no reliability model, or a
#: promise without a ``horizon`` block).
NO_HORIZON_PROMISE = "no horizon promise (no reliability model with a horizon bound)"

# CalibrationResult.to_json: its keys, in order (the CLI's output schema)
JSON_KEYS = ("image", "width", "height", "ok", "reliable", "reason", "horizon_reliable", "horizon_reason", "model", "focal_px", "hfov_deg", "principal_point",
             "rotation", "vertical_axis", "pan_deg", "tilt_deg", "roll_deg", "pitch_deg", "vanishing_points",
             "ranked_vanishing_points", "horizon", "distortion", "log_likelihood", "num_segments", "manhattan_fraction", "cues",
             "predicted_error", "error_bound", "runtime_s")


@camera_record
@dataclass
class CalibrationResult:
    """Everything fR says about one image.  Angles in degrees, lengths in pixels.

    ``camera`` is the estimate (:class:`fr_torch.core.geometry.camera.Camera`: focal length, principal point,
    rotation); ``focal_px``, ``hfov_deg``, ``principal_point``, ``rotation`` (3, 3) world->camera,
    ``pan_deg`` / ``tilt_deg`` / ``roll_deg`` / ``pitch_deg`` and ``vanishing_points`` (3, 3; row i
    = homogeneous VP i (x, y, w), w >= 0) are read-only views of it (:func:`fr_torch.core.geometry.camera.camera_record`).
    ``ok`` is False when no estimate could be made (then ``camera`` and those fields are None and
    ``reason`` says why).  ``reliable`` is False when the estimate exists but should not be
    trusted (too few segments, a Manhattan family nearly empty, or predicted errors above the
    threshold once a reliability model is loaded); ``reason`` lists why.

    ``ranked_vanishing_points`` (M, 3): every vanishing point of the estimate, rows ``(x, y, w)``
    (``w >= 0``), ranked by ``vanishing_point_support`` (M,), the length-weighted posterior mass of
    each family's segments (pixels), most supported first; ``vanishing_point_families`` (M,) says
    which family each is: 0-2 the column of R (1 = vertical), 3.. an Atlanta family (an extra
    horizontal direction, ``atlanta`` option; :mod:`fr_torch.core.geometry.vanishing`).  M = 3 without it.

    ``model``: the fit the estimate comes from, ``manhattan`` (fR's mixture fit: every estimate's,
    the division lens's and the extra families' included); None without an estimate.

    ``horizon`` (:class:`fr_torch.core.geometry.horizon.Horizon`, None without an estimate): the horizon in
    the input image's pixels, where it crosses the left and right borders, and its 90 % bound in %
    of the image height (from ``error_bound``; None without one).

    ``horizon_reliable``: the horizon promise (:class:`fr_torch.core.reliability.bounds.HorizonPromise`)
    holds -- the sanity checks passed and the horizon's 90 % bound (``error_bound["horizon_pct"]``) is
    within its limit (``error_bound["limits"]["horizon_pct"]``, % of the image height); independent of
    ``reliable`` (a horizon can be trusted where the focal length cannot).  ``horizon_reason``
    says why not (empty when it holds).
    """

    image: str
    width: int
    height: int
    ok: bool = True
    reliable: bool = False
    reason: str = ""
    horizon_reliable: bool = False
    horizon_reason: str = ""
    camera: Camera | None = None
    vertical_axis: int = VERTICAL_AXIS
    log_likelihood: float | None = None
    num_segments: int = 0
    manhattan_fraction: float | None = None  # share of total segment length labelled with a family
    segments: np.ndarray | None = None  # (N, 4) the segments used
    labels: np.ndarray | None = None  # (N,) 0, 1, 2 = Manhattan column (1 = vertical), 3 = background
    ranked_vanishing_points: np.ndarray | None = None  # (M, 3) rows (x, y, w), most supported first
    vanishing_point_support: np.ndarray | None = None  # (M,) pixels of segment length
    vanishing_point_families: np.ndarray | None = None  # (M,) 0-2 Manhattan column, 3.. Atlanta family
    cues: dict[str, float] = field(default_factory=dict)
    predicted_error: dict[str, float] | None = None
    # what `reliable` promises (fr_torch.core.reliability.bounds): {"coverage", "focal_pct", "tilt_deg" (the
    # bounds), "limits": {...}}; None without a reliability promise
    error_bound: dict[str, Any] | None = None
    # seconds per image: detect, grid (the k^4 grid, the focal sweep and the lattice passes), refine, cues, total
    runtime_s: dict[str, float] = field(default_factory=dict)
    # the lens model of the estimate: "pinhole" or "division" with its normalised k (fr_torch.core.geometry.lens)
    distortion_model: str = "pinhole"
    distortion_k: float = 0.0
    # the fit the estimate comes from: "manhattan" (fR's mixture fit); None without an estimate
    model: str | None = None

    @property
    def distortion(self) -> dict[str, Any] | None:
        """The estimate's lens model, ``{"model", "k", "centre": [x, y], "radius_px", "bow_pct"}``
        (:func:`fr_torch.core.geometry.lens.distortion_record`; ``model`` ``pinhole`` with k = 0 for a
        pinhole estimate); None without an estimate."""
        if self.camera is None:
            return None
        record = distortion_record(self.distortion_k, self.camera.principal_point, self.width, self.height)
        return dict(record, model=self.distortion_model)

    @property
    def horizon(self) -> Horizon | None:
        """The estimate's horizon in the input image's pixels (:meth:`fr_torch.core.geometry.horizon.Horizon.from_camera`:
        the line ``K^-T R[:, 1]``, through the estimate's lens when it has one), where it crosses the
        borders ``x = 0`` and ``x = w - 1``, and the 90 % bound of its error at the borders in % of
        the image height: the horizon promise's (``error_bound["horizon_pct"]``) where the promise
        has one, else derived from the focal and tilt bounds
        (:func:`fr_torch.core.reliability.bounds.horizon_bound_pct`); None without one; None without
        an estimate."""
        if not self.ok or self.camera is None:
            return None
        bound = None
        if self.error_bound is not None and "horizon_pct" in self.error_bound:
            bound = self.error_bound["horizon_pct"]
        elif self.focal_px is not None and self.tilt_deg is not None:
            bound = horizon_bound_pct(self.error_bound, self.focal_px, self.tilt_deg, self.height)
        return Horizon.from_camera(self.camera, self.distortion_k, bound)

    def _lens(self):
        if self.camera is None or self.focal_px is None:
            raise ValueError(f"{self.image}: no estimate ({self.reason})")
        return self.distortion_k, self.focal_px, self.camera.principal_point, self.width, self.height

    def undistort_points(self, points) -> np.ndarray:
        """Photo pixels (..., 2) -> the estimate's undistorted (pinhole) pixels, where ``K`` and
        ``rotation`` apply (:func:`fr_torch.core.geometry.lens.undistort_points`; unchanged for a
        pinhole estimate).  ValueError without an estimate."""
        k, _, centre, width, height = self._lens()
        return undistort_points(np.asarray(points, np.float64), k, np.asarray(centre), normalising_radius(width, height))

    def distort_points(self, points) -> np.ndarray:
        """Undistorted pixels (..., 2) -> photo pixels (the inverse of :meth:`undistort_points`)."""
        k, _, centre, width, height = self._lens()
        return distort_points(np.asarray(points, np.float64), k, np.asarray(centre), normalising_radius(width, height))

    def opencv(self) -> dict[str, Any]:
        """The estimate as OpenCV's camera matrix and distortion coefficients (a dict that
        ``cv2.FileStorage`` reads as JSON; :func:`fr_torch.core.exports.opencv_camera`: k1, k2
        (k3 where two terms leave more than a pixel) fitted to the division model, the fit's residual
        in pixels beside them).  ValueError without an estimate."""
        return opencv_camera(*self._lens())

    def colmap(self, model: str = "division") -> tuple[str, list[float], dict[str, float]]:
        """COLMAP's camera model, parameters and residual in pixels
        (:func:`fr_torch.core.exports.colmap_camera`): a division estimate as ``SIMPLE_DIVISION``
        (exact, COLMAP >= 4.0; ``model="division"``) or ``RADIAL`` (fitted, ``model="radial"``), a
        pinhole one as ``SIMPLE_PINHOLE``.  ValueError without an estimate, FRInputError for an
        unknown ``model``."""
        return colmap_camera(*self._lens(), model=model)

    def to_kornia(self):
        """The estimate as a ``kornia.geometry.camera.PinholeCamera`` (batch of 1, float64): intrinsics
        ``K`` and extrinsics ``[R | 0]`` (world -> camera, the Manhattan frame; no translation is
        known).  Kornia's pinhole camera has no distortion: apply it to :meth:`undistort_points`'
        pixels, or straighten the photo first (``fr undistort``).  ValueError without an estimate."""
        import kornia.geometry.camera as kornia_camera  # imported on use: kornia adds ~1 s to start-up

        if self.camera is None or self.focal_px is None or self.rotation is None:
            raise ValueError(f"{self.image}: no estimate ({self.reason})")
        intrinsics = torch.eye(4, dtype=torch.float64)
        intrinsics[:3, :3] = torch.as_tensor(self.camera.K)
        extrinsics = torch.eye(4, dtype=torch.float64)
        extrinsics[:3, :3] = torch.as_tensor(self.rotation)
        height, width = torch.tensor([float(self.height)], dtype=torch.float64), torch.tensor([float(self.width)],
                                                                                               dtype=torch.float64)
        return kornia_camera.PinholeCamera(intrinsics[None], extrinsics[None], height, width)

    def to_json(self, include_segments: bool = False) -> dict[str, Any]:
        """JSON-ready dict (the CLI's output schema, keys :data:`JSON_KEYS`; arrays become nested lists)."""
        computed = ("ranked_vanishing_points", "horizon")
        out = {key: copy.deepcopy(getattr(self, key)) for key in JSON_KEYS if key not in computed}
        out["ranked_vanishing_points"] = self.ranked_vanishing_points_json()
        out["horizon_reliable"] = bool(self.horizon_reliable and self.ok)
        if not out["horizon_reliable"] and not self.horizon_reason:  # never "not reliable" without a reason
            out["horizon_reason"] = self.reason if not self.ok and self.reason else NO_HORIZON_PROMISE
        horizon = self.horizon
        out["horizon"] = None if horizon is None else horizon.to_json()
        out = {key: out[key] for key in JSON_KEYS}
        for key in ("rotation", "vanishing_points"):
            if out[key] is not None:
                out[key] = np.asarray(out[key]).tolist()
        if include_segments and self.segments is not None:
            out["segments"] = self.segments.tolist()
            out["labels"] = self.labels.tolist()
        if self.labels is not None:
            out["segments_per_family"] = np.bincount(self.labels, minlength=4).tolist()
        return out

    def ranked_vanishing_points_json(self) -> list[dict[str, Any]] | None:
        """``[{"point": [x, y, w], "support_px": s, "family": k}, ...]`` most supported first (the
        JSON's ``ranked_vanishing_points``), or None without them."""
        if self.ranked_vanishing_points is None:
            return None
        support = self.vanishing_point_support if self.vanishing_point_support is not None else \
            np.full(len(self.ranked_vanishing_points), np.nan)
        families = self.vanishing_point_families if self.vanishing_point_families is not None else \
            np.full(len(self.ranked_vanishing_points), -1)
        return [{"point": np.asarray(p, np.float64).tolist(), "support_px": float(s), "family": int(k)}
                for p, s, k in zip(self.ranked_vanishing_points, support, families)]
