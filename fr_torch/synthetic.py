"""Synthetic Manhattan scenes with exactly known camera: segment sets and rendered images.

Used by the tests, the bundled example image and the benchmarks.  Conventions are those of
:mod:`fr_torch.core.geometry.conventions` (R world->camera, world y = down, pixels x right / y down).
"""
from __future__ import annotations

import cv2
import numpy as np

from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.conventions import image_centre, rotation_from_angles
from fr_torch.core.geometry.lens import distort_points, normalising_radius


def camera_matrix(focal_px: float, width: int, height: int, principal_point=None) -> np.ndarray:
    """K (3, 3) with the principal point at the image centre unless given (pixels)."""
    return Camera(width, height, float(focal_px), principal_point).K


def random_rotation(rng: np.random.Generator, pan=(-45, 45), pitch=(-30, 30), roll=(-10, 10)) -> np.ndarray:
    """World->camera R with uniformly drawn pan / pitch / roll (degrees)."""
    angles = [rng.uniform(*r) for r in (pan, pitch, roll)]
    return rotation_from_angles(*[np.float64(a) for a in angles]).numpy()


def _project(K: np.ndarray, R: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    cam = points_world @ R.T
    uvw = cam @ K.T
    return uvw[..., :2] / uvw[..., 2:3], cam[..., 2]


def synthetic_segments(focal_px: float, rotation: np.ndarray, width: int = 640, height: int = 480,
                       n_per_family: int = 60, noise_px: float = 0.5, clutter_fraction: float = 0.3,
                       seed: int = 0, principal_point=None, min_length_px: float = 15.0,
                       max_length_px: float = 120.0):
    """Segments of the three Manhattan families plus random clutter, as seen by camera (f, R).

    Each Manhattan segment is the image of a 3-D segment parallel to a world axis, placed at a
    random depth in front of the camera and clipped to the image; endpoints get Gaussian noise of
    ``noise_px`` (pixels).  ``clutter_fraction`` of the returned segments are random segments
    with uniform position and orientation.  Returns ``(segments (N, 4), labels (N,))`` with
    labels 0, 1, 2 = world axis (1 = vertical) and 3 = clutter.
    """
    rng = np.random.default_rng(seed)
    K = camera_matrix(focal_px, width, height, principal_point)
    K_inv = np.linalg.inv(K)
    segs, labels = [], []
    for axis in range(3):
        direction = np.zeros(3)
        direction[axis] = 1.0
        made, tries = 0, 0
        while made < n_per_family and tries < 200 * n_per_family:
            tries += 1
            # A random pixel and depth give the 3-D start point; extend along the world axis.
            pixel = np.array([rng.uniform(0, width), rng.uniform(0, height), 1.0])
            depth = rng.uniform(2.0, 10.0)
            start_cam = (K_inv @ pixel) * depth
            start_world = rotation.T @ start_cam
            length_3d = rng.uniform(0.3, 3.0) * rng.choice([-1.0, 1.0])
            end_world = start_world + length_3d * direction
            (uv, z) = _project(K, rotation, np.stack([start_world, end_world]))
            if (z <= 0.1).any():
                continue
            ok, p, q = cv2.clipLine((0, 0, width - 1, height - 1),
                                    tuple(np.round(uv[0]).astype(int)), tuple(np.round(uv[1]).astype(int)))
            if not ok:
                continue
            # Keep the exact (un-rounded) geometry: clip the float segment to the image box.
            a, b = clip_segment(uv[0], uv[1], width - 1, height - 1)
            if a is None:
                continue
            seg_len = np.linalg.norm(b - a)
            if seg_len < min_length_px:
                continue
            if seg_len > max_length_px:  # keep a random sub-segment of bounded length
                t0 = rng.uniform(0, 1 - max_length_px / seg_len)
                a, b = a + t0 * (b - a), a + (t0 + max_length_px / seg_len) * (b - a)
            segs.append(np.concatenate([a, b]))
            labels.append(axis)
            made += 1
    manhattan = np.asarray(segs).reshape(-1, 4)
    n_clutter = int(round(clutter_fraction / max(1e-9, 1 - clutter_fraction) * len(manhattan)))
    centre = np.stack([rng.uniform(0, width, n_clutter), rng.uniform(0, height, n_clutter)], 1)
    angle = rng.uniform(0, np.pi, n_clutter)
    half = rng.uniform(min_length_px, max_length_px, n_clutter)[:, None] / 2
    offset = np.stack([np.cos(angle), np.sin(angle)], 1) * half
    clutter = np.concatenate([centre - offset, centre + offset], 1)
    segments = np.concatenate([manhattan, clutter]) if n_clutter else manhattan
    labels = np.concatenate([np.asarray(labels, int), np.full(n_clutter, 3)])
    segments = segments + rng.normal(0, noise_px, segments.shape) * (noise_px > 0)
    order = rng.permutation(len(segments))
    return segments[order], labels[order]


def distorted_segments(segments: np.ndarray, labels: np.ndarray, k: float, width: int, height: int,
                       piece_px: float = 25.0) -> tuple[np.ndarray, np.ndarray]:
    """The pinhole ``segments`` (N, 4) seen through the division model of ``k`` (normalised by half
    the image diagonal, centre = the image centre :func:`~fr_torch.core.geometry.conventions.image_centre`;
    :mod:`fr_torch.core.geometry.lens`), as a line detector sees a bent edge: each segment becomes
    chords of about ``piece_px`` pixels between points of its bent image (straight pieces tangent
    to the curve).  Returns (pieces (M, 4), their labels (M,)), pieces whose ends both lie in the
    image."""
    centre = np.array(image_centre(width, height))
    radius = normalising_radius(width, height)
    pieces, piece_labels = [], []
    for segment, label in zip(np.asarray(segments, np.float64).reshape(-1, 4), labels):
        a, b = segment[:2], segment[2:]
        count = max(1, int(np.ceil(np.linalg.norm(b - a) / piece_px)))
        points = distort_points(a + np.linspace(0.0, 1.0, count + 1)[:, None] * (b - a), k, centre, radius)
        chords = np.concatenate([points[:-1], points[1:]], 1)
        inside = np.isfinite(chords).all(1) & (chords[:, 0::2] >= 0).all(1) & (chords[:, 0::2] <= width - 1).all(1) \
            & (chords[:, 1::2] >= 0).all(1) & (chords[:, 1::2] <= height - 1).all(1)
        pieces.append(chords[inside])
        piece_labels.append(np.full(int(inside.sum()), label))
    return np.concatenate(pieces).reshape(-1, 4), np.concatenate(piece_labels).astype(int)


def clip_segment(p: np.ndarray, q: np.ndarray, xmax: float, ymax: float):
    """Liang-Barsky clip of the image segment ``p``-``q`` ((2,) pixels each) to ``[0, xmax] x [0, ymax]``:
    its two ends (2,) each, or (None, None) when it lies outside."""
    d = q - p
    t0, t1 = 0.0, 1.0
    for pi, qi in ((-d[0], p[0]), (d[0], xmax - p[0]), (-d[1], p[1]), (d[1], ymax - p[1])):
        if pi == 0:
            if qi < 0:
                return None, None
            continue
        t = qi / pi
        if pi < 0:
            t0 = max(t0, t)
        else:
            t1 = min(t1, t)
        if t0 > t1:
            return None, None
    return p + t0 * d, p + t1 * d


def clip_segment_near(p: np.ndarray, q: np.ndarray, near: float) -> np.ndarray | None:
    """The part (2, 3) of the camera-frame segment ``p``-``q`` ((3,) each) with depth ``z >= near``
    (the same units), or None when all of it lies nearer."""
    if p[2] < near and q[2] < near:
        return None
    if p[2] < near or q[2] < near:
        t = (near - p[2]) / (q[2] - p[2])
        cut = p + t * (q - p)
        p, q = (cut, q) if p[2] < near else (p, cut)
    return np.stack([p, q])


def render_manhattan_room(focal_px: float = 500.0, rotation: np.ndarray | None = None, width: int = 640,
                          height: int = 480, seed: int = 0, noise_sigma: float = 3.0) -> np.ndarray:
    """Render a grey-level image (uint8, H x W) of a box room with tiled walls, floor and ceiling.

    The room is x in [-4, 4], y in [-1.5, 1.5] (down), z in [-4, 8] (world units), camera at the
    origin.  Every wall carries a grid of lines along the two world axes that span it, drawn
    anti-aliased with random grey levels, plus a few furniture-like boxes.  Straight 3-D lines
    stay straight under a pinhole camera, so each visible piece is drawn as an exact chord.
    """
    rotation = np.eye(3) if rotation is None else np.asarray(rotation, np.float64)
    rng = np.random.default_rng(seed)
    K = camera_matrix(focal_px, width, height)
    scale = 4  # supersample for accurate anti-aliasing
    canvas = np.full((height * scale, width * scale), 95, np.uint8)
    x0, x1, y0, y1, z0, z1 = -4.0, 4.0, -1.5, 1.5, -4.0, 8.0

    lines = []
    for y in np.linspace(y0, y1, 7):  # horizontal lines on the side walls and the far/near walls
        lines += [((x0, y, z0), (x0, y, z1)), ((x1, y, z0), (x1, y, z1)),
                  ((x0, y, z1), (x1, y, z1)), ((x0, y, z0), (x1, y, z0))]
    for z in np.linspace(z0, z1, 13):  # verticals on side walls, cross lines on floor and ceiling
        lines += [((x0, y0, z), (x0, y1, z)), ((x1, y0, z), (x1, y1, z)),
                  ((x0, y1, z), (x1, y1, z)), ((x0, y0, z), (x1, y0, z))]
    for x in np.linspace(x0, x1, 9):  # verticals on far/near walls, depth lines on floor/ceiling
        lines += [((x, y0, z1), (x, y1, z1)), ((x, y0, z0), (x, y1, z0)),
                  ((x, y1, z0), (x, y1, z1)), ((x, y0, z0), (x, y0, z1))]
    for _ in range(6):  # boxes standing on the floor
        cx, cz = rng.uniform(x0 + 1, x1 - 1), rng.uniform(1.5, z1 - 1)
        sx, sz, sy = rng.uniform(0.3, 0.9), rng.uniform(0.3, 0.9), rng.uniform(0.4, 1.6)
        corners = [(cx + a * sx, y1 - b * sy, cz + c * sz) for a in (-1, 1) for b in (0, 1) for c in (-1, 1)]
        for i, p in enumerate(corners):
            for q in corners[i + 1:]:
                if sum(abs(u - v) > 1e-9 for u, v in zip(p, q)) == 1:
                    lines.append((p, q))

    for p, q in lines:
        p, q = np.asarray(p, float), np.asarray(q, float)
        pc, qc = rotation @ p, rotation @ q
        front = clip_segment_near(pc, qc, 0.05)
        if front is None:
            continue
        uv = front @ K.T
        uv = uv[:, :2] / uv[:, 2:]
        a, b = clip_segment(uv[0], uv[1], width - 1, height - 1)
        if a is None:
            continue
        a = tuple(int(round((v + 0.5) * scale * 16 - 8)) for v in a)
        b = tuple(int(round((v + 0.5) * scale * 16 - 8)) for v in b)
        cv2.line(canvas, a, b, int(rng.integers(160, 250)), 2 * scale // 2, cv2.LINE_AA, shift=4)
    image = cv2.resize(canvas, (width, height), interpolation=cv2.INTER_AREA).astype(np.float64)
    image += rng.normal(0, noise_sigma, image.shape)
    return np.clip(image, 0, 255).astype(np.uint8)
