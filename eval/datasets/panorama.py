"""Equirectangular (and cube-map) panoramas -> pinhole views with exactly known K and R.

Everything here is tensor code (``torch.nn.functional.grid_sample``), batched over views and
runnable on CPU or CUDA.  Conventions follow :mod:`fr_torch.core.geometry.conventions`; in addition:

Panorama world frame
--------------------
* World ("pano") frame: x, y, z with **y pointing down** (gravity, the panorama is upright),
  z = the direction seen at the **centre column** of the panorama on the horizon row, and
  x = the direction 90 deg to the right of it (seen at column 3W/4).  A direction
  ``d = (cos(lat) sin(lon), -sin(lat), cos(lat) cos(lon))``.
* Longitude ``lon = atan2(d_x, d_z)`` in (-180, 180], increasing to the **right** in the image
  (turning right, as for any non-mirrored panorama); latitude ``lat = asin(-d_y)``, positive
  **up** (the zenith is the top row).
* Pixels: the panorama's W columns tile the full circle and its H rows the full (-90, 90)
  latitude range, with pixel centres at half-pixel offsets::

      lon = ((u + 0.5) / W - 0.5) * 360 deg        lat = (0.5 - (v + 0.5) / H) * 180 deg

  where (u, v) are the column / row of a pixel *centre* (pixel (0, 0)'s centre is (0, 0)).
  This is exactly ``grid_sample``'s ``align_corners=False`` convention with normalised
  coordinates ``gx = lon / 180 deg`` and ``gy = -lat / 90 deg``.  (ZInD's own formula uses
  ``(W - 1)`` instead of ``W``; the difference is at most half a panorama pixel, 0.09 deg at
  2048 px, far below its annotation uncertainty.)  Seams are handled by padding the panorama
  circularly in longitude and across the poles (the row above the top row is the top row
  shifted by W/2), so bilinear and bicubic sampling are continuous everywhere.
* With pan = pitch = roll = 0 (R = I) the camera looks at the centre column, level.

Room (Manhattan) frame and ``manhattan_yaw_deg``
------------------------------------------------
``manhattan_yaw_deg`` is the **longitude of one horizontal Manhattan axis** in the panorama
frame (any of the four, they differ by 90 deg).  The room frame is the pano frame turned right by
that yaw about the vertical: ``d_pano = Ry(yaw) @ d_room`` with ``Ry`` the active rotation of
:func:`fr_torch.core.geometry.conventions.rotation_from_angles` (``Ry(a) @ e_z`` has longitude ``a``).  So the room's
z axis is at longitude ``yaw`` and its x axis at ``yaw + 90``.  Rotations handed to
:func:`render_views` are world->camera **in the room frame** (``X_cam = R @ X_room``); the
renderer uses ``R_pano = R @ Ry(yaw).T``.  With yaw = 0 the room frame is the pano frame.

Pinhole views
-------------
``K = [[f, 0, (w-1)/2], [0, f, (h-1)/2], [0, 0, 1]]`` in the project's pixel convention (pixel
(0, 0)'s centre at (0, 0)), i.e. the principal point is exactly the image centre
(:func:`fr_torch.core.geometry.conventions.image_centre`).  The colour of output pixel (u, v) is the
panorama sampled along the ray ``R_pano.T @ K^-1 @ (u, v, 1)``; so ``K @ R[:, i]`` is exactly
the vanishing point of room axis i, with no half-pixel bias.

Cube maps
---------
:func:`cubemap_to_equirect` converts six 90-deg faces (f = S/2, principal point at the face
centre, i.e. pixel *edges* at normalised +-1: ``align_corners=False``) into an equirectangular
panorama.  Face order is the Matterport / PanoBasic skybox order: 0 = up, 1..4 = the horizontal
faces turning right (face 1 at lon 0, face k at lon (k-1)*90), 5 = down.  The up face's bottom
edge adjoins face 1's top edge and the down face's top edge adjoins face 1's bottom edge
(checked on ``matterport3d_skybox_sample``; see :func:`cube_face_rotations`).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from fr_torch.core.geometry.conventions import image_centre, intrinsics, rotation_from_angles
from fr_torch.core.geometry.lens import normalising_radius, undistort_points

__all__ = [
    "to_chw_float",
    "yaw_rotation",
    "direction_from_lonlat",
    "lonlat_from_direction",
    "equirect_pixel_from_direction",
    "view_rays",
    "view_grid",
    "sample_equirect",
    "render_views",
    "cube_face_rotations",
    "cubemap_to_equirect",
    "load_cubemap",
    "load_panorama",
    "save_rgb",
    "angles_rotation",
]


# --------------------------------------------------------------------------- helpers

def to_chw_float(pano, device=None) -> tuple[torch.Tensor, bool]:
    """(H, W, C) uint8 numpy / tensor or (C, H, W) float tensor -> (C, H, W) float32 on device.

    Returns the tensor and whether the input was 8-bit (then outputs are rounded back to uint8).
    A numpy / uint8 input is taken as (H, W, C); a floating tensor with 3 dims whose first dim
    is <= 4 and last dim > 4 is taken as (C, H, W) already.
    """
    t = torch.as_tensor(np.ascontiguousarray(pano)) if isinstance(pano, np.ndarray) else pano
    is_u8 = t.dtype == torch.uint8
    if t.ndim == 2:
        t = t[..., None]
    if is_u8 or not (t.shape[0] <= 4 and t.shape[-1] > 4):
        t = t.permute(2, 0, 1)
    return t.to(device=device, dtype=torch.float32).contiguous(), is_u8


def yaw_rotation(yaw_deg, dtype=torch.float64, device=None) -> torch.Tensor:
    """Ry(yaw): active rotation about the (down-pointing) world y axis, (..., 3, 3).

    ``Ry(yaw) @ e_z`` has longitude ``yaw`` (turns right).  Equal to the camera-to-world rotation
    of a level camera with pan = yaw, i.e. ``rotation_from_angles(yaw, 0, 0).T``.
    """
    yaw = torch.as_tensor(yaw_deg, dtype=dtype, device=device)
    return rotation_from_angles(yaw, torch.zeros_like(yaw), torch.zeros_like(yaw)).transpose(-1, -2)


def direction_from_lonlat(lon_rad: torch.Tensor, lat_rad: torch.Tensor) -> torch.Tensor:
    """Unit direction(s) (..., 3) in the pano frame (y down) from longitude / latitude (radians)."""
    c = torch.cos(lat_rad)
    return torch.stack([c * torch.sin(lon_rad), -torch.sin(lat_rad), c * torch.cos(lon_rad)], -1)


def lonlat_from_direction(d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(lon, lat) in radians of direction(s) d (..., 3) (need not be unit)."""
    lon = torch.atan2(d[..., 0], d[..., 2])
    lat = torch.atan2(-d[..., 1], torch.hypot(d[..., 0], d[..., 2]))
    return lon, lat


def equirect_pixel_from_direction(d: torch.Tensor, width: int, height: int) -> torch.Tensor:
    """Panorama pixel-centre coordinates (u, v), (..., 2), of direction(s) d (module convention)."""
    lon, lat = lonlat_from_direction(d)
    u = (lon / (2 * math.pi) + 0.5) * width - 0.5
    v = (0.5 - lat / math.pi) * height - 0.5
    return torch.stack([u, v], -1)


def view_rays(rotations: torch.Tensor, focal_px: torch.Tensor, size: tuple[int, int],
              manhattan_yaw_deg: float | torch.Tensor = 0.0, device=None,
              dtype=torch.float64, distortion_k=None) -> torch.Tensor:
    """Pano-frame ray directions (V, h, w, 3) (not normalised) of every output pixel centre.

    ray(u, v) = Ry(yaw) @ R.T @ K^-1 @ (u, v, 1), with K's principal point the image centre
    ((w-1)/2, (h-1)/2) (:func:`fr_torch.core.geometry.conventions.image_centre`).
    ``distortion_k`` (V,) or None: views through the division model of these k
    (:mod:`fr_torch.core.geometry.lens`, centre the principal point): pixel (u, v) is undistorted first.
    """
    w, h = size
    rotations = torch.as_tensor(rotations, dtype=dtype, device=device).reshape(-1, 3, 3)
    focal = torch.as_tensor(focal_px, dtype=dtype, device=device).reshape(-1).expand(rotations.shape[0])
    K = intrinsics(focal, torch.tensor(image_centre(w, h), dtype=dtype, device=device))
    yaw = torch.as_tensor(manhattan_yaw_deg, dtype=dtype, device=device).reshape(-1).expand(rotations.shape[0])
    cam_to_pano = yaw_rotation(yaw, dtype=dtype, device=device) @ rotations.transpose(-1, -2)
    M = cam_to_pano @ torch.linalg.inv(K)  # (V, 3, 3)
    vs, us = torch.meshgrid(torch.arange(h, dtype=dtype, device=device),
                            torch.arange(w, dtype=dtype, device=device), indexing="ij")
    pix = torch.stack([us, vs, torch.ones_like(us)], -1)  # (h, w, 3)
    if distortion_k is None:
        return torch.einsum("vij,hwj->vhwi", M, pix)
    k = torch.as_tensor(distortion_k, dtype=dtype, device=device).reshape(-1, 1, 1, 1).expand(rotations.shape[0], 1, 1, 1)
    centre = torch.tensor(image_centre(w, h), dtype=dtype, device=device)
    undistorted = undistort_points(pix[None, ..., :2], k[..., 0], centre, normalising_radius(w, h))
    pix = torch.cat([undistorted, torch.ones_like(undistorted[..., :1])], -1)  # (V, h, w, 3)
    return torch.einsum("vij,vhwj->vhwi", M, pix)


def view_grid(rotations, focal_px, size, manhattan_yaw_deg=0.0, device=None, distortion_k=None) -> torch.Tensor:
    """Normalised equirect sampling grid (V, h, w, 2): gx = lon / pi, gy = -lat / (pi / 2)."""
    d = view_rays(rotations, focal_px, size, manhattan_yaw_deg, device=device, distortion_k=distortion_k)
    lon, lat = lonlat_from_direction(d)
    return torch.stack([lon / math.pi, -lat / (math.pi / 2)], -1)


def _pad_sphere(pano: torch.Tensor, pad: int) -> torch.Tensor:
    """Pad (C, H, W) circularly in longitude and across the poles by ``pad`` pixels."""
    C, H, W = pano.shape
    wide = torch.cat([pano[..., W - pad:], pano, pano[..., :pad]], -1)  # (C, H, W + 2p)
    # Across a pole, row -1-i is row i seen from the opposite longitude (shift by W/2).
    shift = W // 2
    top = torch.roll(wide[:, :pad].flip(1), shifts=shift, dims=-1)
    bottom = torch.roll(wide[:, H - pad:].flip(1), shifts=shift, dims=-1)
    return torch.cat([top, wide, bottom], 1)


def sample_equirect(pano_chw: torch.Tensor, grid: torch.Tensor, mode: str = "bilinear",
                    pad: int = 3) -> torch.Tensor:
    """Sample a (C, H, W) float panorama at a normalised grid (V, h, w, 2) -> (V, C, h, w).

    ``grid`` uses the unpadded panorama's align_corners=False normalisation (gx = lon/pi,
    gy = -lat/(pi/2)); the panorama is padded around the sphere so that the seam and the poles
    interpolate correctly.
    """
    C, H, W = pano_chw.shape
    padded = _pad_sphere(pano_chw, pad)
    Hp, Wp = padded.shape[-2:]
    # unpadded normalised -> pixel centre -> padded pixel -> padded normalised (align_corners=False)
    u = (grid[..., 0] + 1) * W / 2 - 0.5 + pad
    v = (grid[..., 1] + 1) * H / 2 - 0.5 + pad
    g = torch.stack([(u + 0.5) * 2 / Wp - 1, (v + 0.5) * 2 / Hp - 1], -1).to(padded.dtype)
    V = g.shape[0]
    return F.grid_sample(padded.unsqueeze(0).expand(V, -1, -1, -1), g, mode=mode,
                         padding_mode="border", align_corners=False)


def render_views(pano, rotations, focal_px, size: tuple[int, int] = (640, 480),
                 manhattan_yaw_deg: float = 0.0, device=None, mode: str = "bilinear",
                 chunk: int = 8, distortion_k=None):
    """Render pinhole views from an equirectangular panorama.

    pano: (H, W, 3) uint8 (numpy or tensor) or (C, H, W) float tensor; rotations: (V, 3, 3)
    world->camera in the room frame (see module docstring); focal_px: (V,) or scalar;
    size: (w, h).  Returns (V, h, w, C) uint8 (numpy) for 8-bit input, else a float tensor
    (V, C, h, w).  ``mode``: ``bilinear`` (default: geometrically exact, it reproduces linear
    ramps) or ``bicubic`` (sharper; results clamped to 0..255; PyTorch's a = -0.75 kernel moves
    linear ramps by up to 0.05 panorama pixels, i.e. < 0.01 deg on a 2048-wide panorama).
    ``distortion_k`` (V,) or None: render through the division model of these k (:func:`view_rays`).
    """
    device = torch.device(device) if device is not None else torch.device("cpu")
    pano_t, is_u8 = to_chw_float(pano, device)
    rotations = torch.as_tensor(rotations, dtype=torch.float64).reshape(-1, 3, 3)
    V = rotations.shape[0]
    focal = torch.as_tensor(focal_px, dtype=torch.float64).reshape(-1).expand(V)
    outs = []
    for s in range(0, V, chunk):
        k = None if distortion_k is None else torch.as_tensor(distortion_k, dtype=torch.float64).reshape(-1)[s:s + chunk]
        grid = view_grid(rotations[s:s + chunk].to(device), focal[s:s + chunk].to(device), size,
                         manhattan_yaw_deg, device=device, distortion_k=k)
        outs.append(sample_equirect(pano_t, grid, mode=mode))
    out = torch.cat(outs, 0)
    if not is_u8:
        return out
    return out.clamp(0, 255).round().to(torch.uint8).permute(0, 2, 3, 1).cpu().numpy()


# --------------------------------------------------------------------------- cube maps

def cube_face_rotations(dtype=torch.float64) -> torch.Tensor:
    """World->camera rotations (6, 3, 3) of the skybox faces: 0 up, 1..4 around (turning right), 5 down.

    Up face: pitch +90 (its image bottom points to face 1); down face: pitch -90 (image top
    points to face 1); face k in 1..4: pan (k-1)*90.
    """
    pan = torch.tensor([0.0, 0.0, 90.0, 180.0, 270.0, 0.0], dtype=dtype)
    pitch = torch.tensor([90.0, 0.0, 0.0, 0.0, 0.0, -90.0], dtype=dtype)
    return rotation_from_angles(pan, pitch, torch.zeros_like(pan))


def _pad_cube_faces(faces: torch.Tensor, R: torch.Tensor, pad: int) -> torch.Tensor:
    """Faces (6, C, S, S) grown by ``pad`` pixels on each side with pixels of the neighbour faces.

    The padded face keeps f = S/2 and covers +-(S + 2 pad)/S in normalised coordinates, so
    interpolation near a cube edge uses true neighbours instead of clamping.
    """
    n, C, S, _ = faces.shape
    Sp = S + 2 * pad
    c = (torch.arange(Sp, dtype=torch.float64, device=faces.device) - pad + 0.5) / S * 2 - 1
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    ring = torch.zeros(Sp, Sp, dtype=torch.bool, device=faces.device)
    ring[:pad], ring[-pad:], ring[:, :pad], ring[:, -pad:] = True, True, True, True
    out = F.pad(faces, (pad, pad, pad, pad))
    for k in range(n):
        cam = torch.stack([xx[ring], yy[ring], torch.ones_like(xx[ring])], -1)  # (N, 3) in face k
        world = cam @ R[k]  # R^T @ cam as row vectors
        other = torch.einsum("fij,nj->fni", R, world)  # in every face's frame
        z = other[..., 2].clone()
        z[k] = -math.inf  # the ring lies outside face k
        j = z.argmax(0)
        vals = torch.zeros(C, len(j), dtype=faces.dtype, device=faces.device)
        for jj in j.unique().tolist():
            m = j == jj
            cj = other[jj][m]
            g = (cj[:, :2] / cj[:, 2:3]).to(faces.dtype).view(1, 1, -1, 2)
            vals[:, m] = F.grid_sample(faces[jj:jj + 1], g, mode="bilinear", padding_mode="border",
                                       align_corners=False)[0, :, 0]
        out[k][:, ring] = vals
    return out


def cubemap_to_equirect(faces, width: int | None = None, device=None, mode: str = "bilinear"):
    """Six square faces (6, S, S, C) uint8 (or (6, C, S, S) float) -> equirect panorama.

    Output: (H, W, C) uint8 numpy (W = 4 S by default, H = W / 2) for 8-bit input, else
    (C, H, W) float tensor.  Faces are pinhole 90-deg views (f = S/2, pixel edges at +-1).
    """
    device = torch.device(device) if device is not None else torch.device("cpu")
    faces_t = torch.as_tensor(np.ascontiguousarray(faces)) if isinstance(faces, np.ndarray) else faces
    is_u8 = faces_t.dtype == torch.uint8
    if is_u8:
        faces_t = faces_t.permute(0, 3, 1, 2)
    faces_t = faces_t.to(device=device, dtype=torch.float32)
    S = faces_t.shape[-1]
    W = width or 4 * S
    H = W // 2
    us = (torch.arange(W, dtype=torch.float64, device=device) + 0.5) / W - 0.5
    vs = 0.5 - (torch.arange(H, dtype=torch.float64, device=device) + 0.5) / H
    lat, lon = torch.meshgrid(vs * math.pi, us * 2 * math.pi, indexing="ij")
    d = direction_from_lonlat(lon, lat)  # (H, W, 3)
    R = cube_face_rotations().to(device)  # (6, 3, 3)
    padded = _pad_cube_faces(faces_t, R, pad=2 if mode == "bicubic" else 1)
    scale = S / padded.shape[-1]  # face-normalised (+-1 at the face edges) -> padded-normalised
    cam = torch.einsum("fij,hwj->fhwi", R, d)  # direction in each face's camera frame
    face = cam[..., 2].argmax(0)  # the face whose optical axis is closest: largest forward component
    out = torch.zeros(faces_t.shape[1], H, W, dtype=torch.float32, device=device)
    for k in range(6):
        mask = face == k
        if not mask.any():
            continue
        ck = cam[k][mask]  # (N, 3)
        g = (ck[:, :2] / ck[:, 2:3] * scale).to(torch.float32).view(1, 1, -1, 2)
        vals = F.grid_sample(padded[k:k + 1], g, mode=mode, padding_mode="border", align_corners=False)
        out[:, mask] = vals[0, :, 0]
    if not is_u8:
        return out
    return out.clamp(0, 255).round().to(torch.uint8).permute(1, 2, 0).cpu().numpy()


def load_cubemap(folder: str | Path, pattern: str = "*skybox{k}*") -> np.ndarray:
    """Read six skybox faces ``skybox0..5`` from a folder as (6, S, S, 3) uint8 RGB."""
    folder = Path(folder)
    faces = []
    for k in range(6):
        files = sorted(folder.glob(pattern.format(k=k)))
        if not files:
            raise FileNotFoundError(f"{folder}: no face matching {pattern.format(k=k)}")
        faces.append(load_panorama(files[0]))
    return np.stack(faces)


def load_panorama(path: str | Path) -> np.ndarray:
    """Read an image as (H, W, 3) uint8 **RGB**."""
    data = np.fromfile(str(path), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def save_rgb(path: str | Path, image_rgb: np.ndarray, quality: int = 95) -> None:
    """Write an (H, W, 3) uint8 RGB image (JPEG quality / PNG by extension)."""
    path = Path(path)
    params = [cv2.IMWRITE_JPEG_QUALITY, quality] if path.suffix.lower() in (".jpg", ".jpeg") else []
    ok, buf = cv2.imencode(path.suffix, cv2.cvtColor(image_rgb, cv2.COLOR_RGB2BGR), params)
    if not ok:
        raise ValueError(f"could not encode {path}")
    buf.tofile(str(path))


def angles_rotation(pan_deg: Sequence[float], pitch_deg: Sequence[float], roll_deg: Sequence[float]) -> torch.Tensor:
    """Convenience: world->camera R (V, 3, 3), float64, from per-view angles (degrees)."""
    return rotation_from_angles(torch.as_tensor(pan_deg, dtype=torch.float64),
                                torch.as_tensor(pitch_deg, dtype=torch.float64),
                                torch.as_tensor(roll_deg, dtype=torch.float64))
