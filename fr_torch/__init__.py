"""fR in PyTorch: reliable single-image estimation of focal length and camera rotation.

Pipeline (one module each): segments -> likelihood -> search -> reliability, wrapped by the
estimator; conventions in :mod:`fr_torch.camera`.
"""
from .camera import VERTICAL_AXIS, Camera, angles_from_rotation, focal_from_hfov, hfov_from_focal, rotation_from_angles
from .estimator import CalibrationResult, FREstimator, calibrate
from .segments import FRInputError, SegmentFilter, detect_segments

__all__ = [
    "VERTICAL_AXIS", "Camera", "CalibrationResult", "FREstimator", "FRInputError", "SegmentFilter",
    "angles_from_rotation",
    "calibrate", "detect_segments", "focal_from_hfov", "hfov_from_focal", "rotation_from_angles",
]
__version__ = "0.1.0"
