"""The common interface every calibration method implements, and the method registry.

A method is any object with a ``name`` and ``estimate(image, meta) -> CameraEstimate``.  Methods
are looked up by name (``fr``, ``fast-fr``, ``lee2009``, ...) in :data:`CALIBRATORS`, which reads
the entry points of group ``fr_torch.calibrators`` of every installed package, or by import path
(``"my_package.my_module:MyCalibrator"``), so a third party plugs one in without editing this
project (see :mod:`fr_torch.registry` and ``examples/fr_plugin_example``)::

    fr eval --dataset yud --methods fr,my_package.my_module:MyCalibrator

Conventions for every field are those of :mod:`fr_torch.core.geometry.conventions` (pixels, degrees, R world->camera
with x right / y down / z forward, vertical Manhattan direction in column 1).
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from fr_torch.core.geometry.camera import Camera, camera_record
from fr_torch.registry import Registry


@dataclass
class ImageMeta:
    """What a method may know about an image besides its pixels.

    ``segments``: optional (N, 4) array of line segments [x1, y1, x2, y2] in pixels (for methods
    that take segments, e.g. the oracle run on hand-labelled lines).  ``focal_px`` and
    ``principal_point``: known intrinsics, if any (None = unknown / image centre).
    """

    name: str = ""
    width: int = 0
    height: int = 0
    focal_px: float | None = None
    principal_point: tuple[float, float] | None = None
    segments: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)


@camera_record
@dataclass
class CameraEstimate:
    """One method's answer for one image.

    ``camera``: what the method estimated, as one :class:`fr_torch.core.geometry.camera.Camera` of the image
    (``Camera(width, height, focal_px, principal_point, rotation)``): ``focal_px=None`` for a method
    that estimates only the orientation, ``rotation=None`` for one that estimates only the focal
    length, ``Camera.from_angles(..., roll_deg=, tilt_deg=)`` (``pan_known=False``) for one that
    estimates only the horizon (gravity), None for a failure.  ``focal_px``, ``hfov_deg``,
    ``rotation`` ((3, 3) world->camera, vertical in column 1; None unless the whole orientation is
    known), ``roll_deg``, ``tilt_deg``, ``pitch_deg``, ``pan_deg`` are read-only views of it; None
    means "this method does not estimate it".

    ``ranked_vanishing_points``: every vanishing point the method found, (M, 3) float64, row =
    homogeneous point ``(x, y, w)`` in the image's pixels (``w >= 0``; ``w = 0`` at infinity), ranked
    by the method's own confidence, most confident first (the VP task scores the first as many as
    were labelled; ``docs/vp.md``).  None: the method ranks none, and the VP task takes the
    camera's three Manhattan vanishing points ``K R`` in column order.  A failed estimate may keep
    the points it found (e.g. VPs without a focal length).

    ``ok`` is False when the method failed (no vanishing point found, bad input...); ``reason``
    then says why.  Failed estimates are counted by the tables, never silently dropped.
    """

    method: str
    camera: Camera | None = None
    predicted_error: dict[str, float] | None = None  # {"roll_deg", "tilt_deg", "focal_pct"}
    reliable: bool | None = None
    runtime_s: float = float("nan")
    ok: bool = True
    reason: str = ""
    extra: dict[str, Any] = field(default_factory=dict)
    ranked_vanishing_points: np.ndarray | None = None

    @classmethod
    def failure(cls, method: str, reason: str, runtime_s: float = float("nan")) -> "CameraEstimate":
        return cls(method=method, ok=False, reason=reason, runtime_s=runtime_s, reliable=False)


@runtime_checkable
class Calibrator(Protocol):
    """What every method implements (fR, Fast-fR, other published methods, CTRL-C, external predictions)."""

    name: str

    def estimate(self, image: np.ndarray | None, meta: ImageMeta) -> CameraEstimate:
        """Estimate the camera of one image (H x W x 3 uint8 BGR, or H x W grey; may be None
        for methods that only read ``meta``)."""
        ...


def is_calibrator_class(cls: type) -> bool:
    """A class implementing :class:`Calibrator`: it has an ``estimate`` method (``name`` may be set
    by its constructor; the built object is checked in full by :func:`get_calibrator`)."""
    return callable(getattr(cls, "estimate", None))


# Calibrators by name: registered in code (``register``), entry points of group
# ``fr_torch.calibrators`` (this project's own methods too, see pyproject.toml), or "module:attr"
# naming a Calibrator class or a declared factory (fr_torch.registry.Registry.factory).
CALIBRATORS: Registry[Calibrator] = Registry("method", group="fr_torch.calibrators", implements=is_calibrator_class,
                                             protocol="a class with an estimate(image, meta) method")


def register(name: str) -> Callable:
    """Decorator: register a factory (class or function returning a Calibrator) under ``name``."""
    return CALIBRATORS.register(name)


def available_methods() -> list[str]:
    """Names of all registered methods (entry points included, listed without importing them)."""
    return CALIBRATORS.names()


def get_calibrator(spec: str, offered: dict[str, Any] | None = None, **kwargs) -> Calibrator:
    """Build a method from a spec: registered name or import path ``module:attribute``, with
    options in brackets passed to the factory as keyword arguments (strings): ``fr[measure=a]``,
    ``fast-fr[detector=mcmlsd]`` (see :func:`fr_torch.registry.parse_method_spec`).
    ``kwargs`` are passed too (and override the spec's); ``offered`` options only to a factory that
    takes them (:meth:`fr_torch.registry.Registry.create`; ``docs/plugins-options.md``)."""
    method = CALIBRATORS.create(spec, offered=offered, **kwargs)
    if not isinstance(method, Calibrator):
        raise ValueError(f"{spec!r} did not produce a Calibrator (needs .name and .estimate())")
    return method


class Timer:
    """Context manager measuring wall time in seconds (``with Timer() as t: ...; t.seconds``)."""

    def __enter__(self):
        self._start = time.perf_counter()
        self.seconds = float("nan")
        return self

    def __exit__(self, *exc):
        self.seconds = time.perf_counter() - self._start
        return False


class TimedCalibrator:
    """Base for methods that implement ``_estimate(image, meta)``: :meth:`estimate` calls it and
    records its wall time (seconds) in ``runtime_s``."""

    def estimate(self, image: np.ndarray | None, meta: ImageMeta) -> CameraEstimate:
        with Timer() as timer:
            result = self._estimate(image, meta)
        result.runtime_s = timer.seconds
        return result

    def _estimate(self, image: np.ndarray | None, meta: ImageMeta) -> CameraEstimate:
        raise NotImplementedError
