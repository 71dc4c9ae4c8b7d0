"""``synthetic-streets``: rendered street scenes with an exactly known camera and horizon, several
horizontal directions that are not all orthogonal, curved facades and clutter.

What it is for: choices that must be learned for street photos (issue 67) are learned on the
``train`` split and reported on the held-out ``test`` split; no street photo set with a training
split exists here, and the 25 ``ecd-tune`` photos stay for final reports only.

Build (deterministic: the same files from the same seed on every machine with the same OpenCV)::

    python -m fr_eval.datasets.synthetic_streets --out data_local/synthetic-streets --seed 0 --train 200 --test 200
    fr eval --dataset synthetic-streets --split test --methods fr,fast-fr
    fr eval --task horizon --dataset synthetic-streets --split test --methods fr,lee2009

Scene ``i`` of a split is drawn from ``np.random.default_rng([seed, SPLIT_OFFSETS[split] + i])``, so
train and test never share a scene and a scene does not depend on how many others are built.

World frame (:mod:`fr_torch.core.geometry.conventions`): metres, y = down (gravity), the ground is
``y = 0``; the street runs along z (azimuth 0), x across it.  An azimuth ``a`` (degrees) is the
horizontal direction ``(sin a, 0, cos a)``, the camera's pan convention.  Each scene has a set of
2-4 horizontal **directions** (azimuths mod 180), not all orthogonal: ``{0, b}`` with b 30-80 deg
from the street, or ``{0, 90}`` plus one or two directions at least 12 deg from the others.

* **Blocks**: prisms standing on the ground along both sides of the street, footprints that are
  parallelograms whose front and depth edges take two of the scene's directions (every direction is
  used), facades with window grids, doors and floor bands; with probability 0.35 one block is
  **curved**: a circular-segment footprint whose facade's horizontal lines are circles (no
  vanishing point; their tangents vote for the horizon only).
* **Clutter**: trees (a vertical trunk, an irregular crown with short random dark strokes), cars
  (boxes at random azimuths, not counted as directions), lamp posts (vertical), the road's lane
  marks (azimuth 0) and the sidewalk's paving joints (0, and 90 when 90 is a direction).
* **Sky and ground**: per pixel from the ray: a haze-to-blue sky gradient, the ground with fog.

Camera: at height 1.3-1.9 m (one in five scenes 3-8 m) on the street at z = 0; image size from
:data:`SIZES` (landscape and portrait); FOV across the long side ~ U[30, 110] deg; pan along the
street (+-35 deg) for half the views, else uniform; pitch ~ U[-15, 25] (positive looks up: streets are mostly seen from below), roll ~
U[-8, 8]; ``R.T = Ry(pan) Rx(pitch) Rz(roll)`` (:func:`fr_torch.core.geometry.conventions.rotation_from_angles`),
principal point the image centre ``((w - 1) / 2, (h - 1) / 2)``.

Layout (the ``fr make-dataset`` one, :mod:`fr_eval.datasets.make_dataset`, read by
:class:`fr_eval.datasets.panoviews.PanoViews`): ``images/<split>_NNNN.jpg`` (quality 95), ``gt.csv``
(:data:`fr_eval.datasets.panoviews.GT_COLUMNS`, R in the street frame, ``manhattan_known`` False:
with more than three directions the Manhattan frame is not ground truth, so the loaded camera has
``pan_known=False``; plus :data:`EXTRA_COLUMNS`), ``dataset.json``, ``contact_sheet.png``.  The
true horizon is the camera's, ``K^-T R[:, 1]`` (the horizon task's ``frame`` definition): every
horizontal direction's vanishing point ``K R (sin a, 0, cos a)`` lies on it.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from fr_eval.datasets.make_dataset import contact_sheet
from fr_eval.datasets.panorama import save_rgb
from fr_eval.datasets.panoviews import GT_COLUMNS, R_COLUMNS, PanoViews, dataset_folder
from fr_eval.datasets.registry import CalibrationSample, register_dataset
from fr_torch.core.geometry.conventions import focal_from_hfov, hfov_from_focal, horizon_angles, rotation_from_angles
from fr_torch.synthetic import camera_matrix, clip_segment, clip_segment_near

NAME = "synthetic-streets"
#: Scene index offset of each split (module docstring).
SPLIT_OFFSETS = {"train": 0, "test": 1_000_000}
#: Image sizes (width, height), pixels: landscape and portrait.
SIZES = ((640, 480), (480, 640), (720, 480), (480, 720), (800, 450), (450, 800))
FOV_RANGE = (30.0, 110.0)  # degrees across the long side
PITCH_RANGE = (-15.0, 25.0)  # degrees, positive looks up: streets are mostly seen from below
ROLL_RANGE = (-8.0, 8.0)  # degrees
#: Columns of ``gt.csv`` beyond :data:`GT_COLUMNS`: ``scene`` (index in the rng seed), ``n_directions``
#: (the scene's horizontal directions of straight building edges), ``directions_deg`` (their
#: azimuths, ``;``-separated), ``n_directions_in_view`` / ``directions_in_view_deg`` (those whose
#: visible facade outlines are at least :data:`IN_VIEW_MIN_PX` long in the image, occlusion
#: ignored), ``curved`` (a curved facade in the scene), ``fov_long_deg``, ``camera_height_m``.
EXTRA_COLUMNS = ["scene", "n_directions", "directions_deg", "n_directions_in_view", "directions_in_view_deg",
                 "curved", "fov_long_deg", "camera_height_m"]
IN_VIEW_MIN_PX = 150.0
NEAR = 0.1  # metres: polygons are clipped to camera depth z >= NEAR
ROAD_HALF = (4.0, 8.0)  # metres, half the road's width
SIDEWALK = (2.0, 4.5)  # metres
STREET_HALF_LENGTH = 160.0  # metres of blocks either side of the camera along the street
LIGHT = np.array([0.5, -0.8, 0.3]) / np.linalg.norm([0.5, -0.8, 0.3])  # towards the sun (world, y down)


def azimuth_vector(azimuth_deg: float) -> np.ndarray:
    """The horizontal unit direction (3,) ``(sin a, 0, cos a)`` of azimuth ``a`` degrees (world frame)."""
    a = math.radians(azimuth_deg)
    return np.array([math.sin(a), 0.0, math.cos(a)])


def scene_directions(rng: np.random.Generator) -> list[float]:
    """2-4 horizontal directions (azimuths in [0, 180) degrees), the street's (0) first, not all
    orthogonal (module docstring)."""
    count = int(rng.integers(2, 5))
    if count == 2:
        return [0.0, float(rng.uniform(30.0, 80.0) * rng.choice([-1.0, 1.0]) % 180.0)]
    directions = [0.0, 90.0]
    while len(directions) < count:
        a = float(rng.uniform(0.0, 180.0))
        if all(_angle_between(a, d) >= 12.0 for d in directions):
            directions.append(a)
    return directions


def _angle_between(a: float, b: float) -> float:
    """Angle (degrees, [0, 90]) between two undirected horizontal directions given as azimuths."""
    d = abs(a - b) % 180.0
    return min(d, 180.0 - d)


@dataclass
class Block:
    """A prism standing on the ground: ``footprint`` (M, 2) convex polygon of world ``(x, z)``
    (metres), ``height`` (m), facade colour (RGB 0-255), windows every ``bay`` m along and
    ``floor`` m up, ``edge_azimuth`` (M,) the azimuth of each footprint edge (NaN for the facets of
    a curved facade)."""

    footprint: np.ndarray
    height: float
    colour: np.ndarray
    glass: np.ndarray
    bay: float
    floor: float
    window: tuple[float, float]  # window width, height (m)
    edge_azimuth: np.ndarray

    def key(self, eye: np.ndarray) -> float:
        return float(np.min(np.linalg.norm(self.footprint - eye, axis=1)))


@dataclass
class Box:
    """A car: body and cabin boxes, centre ``(x, z)`` on the ground, azimuth (deg), sizes (m)."""

    centre: np.ndarray
    azimuth: float
    colour: np.ndarray

    def key(self, eye: np.ndarray) -> float:
        return float(np.linalg.norm(self.centre - eye)) - 2.0


@dataclass
class Tree:
    """A tree (or, with ``crown`` 0, a lamp post): trunk at ground ``(x, z)``, trunk height (m),
    crown radius (m), colour."""

    base: np.ndarray
    trunk: float
    crown: float
    colour: np.ndarray
    seed: int

    def key(self, eye: np.ndarray) -> float:
        return float(np.linalg.norm(self.base - eye)) - self.crown


@dataclass
class StreetScene:
    """One scene and its camera (module docstring for the frames).

    ``rotation`` (3, 3) world->camera (``pan_deg`` its pan, degrees); ``eye`` (3,) the camera centre (world, metres; y < 0 is above
    the ground); ``focal_px``; image ``width`` x ``height`` pixels; ``directions`` (azimuths, deg);
    ``curved``: a curved facade; ``objects`` blocks, cars and trees; colours and noise of the render."""

    width: int
    height: int
    focal_px: float
    rotation: np.ndarray
    eye: np.ndarray
    fov_long_deg: float
    pan_deg: float
    directions: list[float]
    curved: bool
    road_half: float
    sidewalk: float
    objects: list = field(default_factory=list)
    sky: tuple[np.ndarray, np.ndarray] = (np.zeros(3), np.zeros(3))
    noise_sigma: float = 3.0
    render_seed: int = 0

    @property
    def K(self) -> np.ndarray:
        """(3, 3) intrinsics, principal point the image centre."""
        return camera_matrix(self.focal_px, self.width, self.height)


# --------------------------------------------------------------------------- sampling

def sample_scene(seed: int, index: int) -> StreetScene:
    """Scene ``index`` of generator seed ``seed`` (module docstring; deterministic)."""
    rng = np.random.default_rng([int(seed), int(index)])
    directions = scene_directions(rng)
    road_half, sidewalk = float(rng.uniform(*ROAD_HALF)), float(rng.uniform(*SIDEWALK))
    curved_at = int(rng.integers(0, 6)) if rng.uniform() < 0.35 else -1
    objects: list = []
    unused = list(directions[1:])
    for side in (-1.0, 1.0):
        z = -STREET_HALF_LENGTH
        count = 0
        while z < STREET_HALF_LENGTH:
            if side > 0 and count == curved_at:
                block = _curved_block(rng, side, z, road_half + sidewalk)
            else:
                block = _block(rng, side, z, road_half + sidewalk, directions, unused)
            objects.append(block)
            z = float(block.footprint[:, 1].max()) + (rng.uniform(12, 20) if rng.uniform() < 0.15 else rng.uniform(0, 4))
            count += 1
    for _ in range(int(rng.integers(0, 9))):  # cars: on the road or parked, random azimuths
        x = rng.uniform(-road_half + 1.2, road_half - 1.2)
        z = rng.uniform(6.0, 60.0) * rng.choice([-1.0, 1.0])
        objects.append(Box(np.array([x, z]), float(rng.uniform(0, 360)), rng.integers(20, 230, 3).astype(float)))
    for _ in range(int(rng.integers(0, 14))):  # trees and lamp posts on the sidewalks
        x = rng.choice([-1.0, 1.0]) * (road_half + rng.uniform(0.5, sidewalk - 0.5))
        z = rng.uniform(-80.0, 80.0)
        if abs(z) < 2.0 and abs(x) < 3.0:
            continue
        tree = rng.uniform() < 0.75
        objects.append(Tree(np.array([x, z]), float(rng.uniform(2.0, 3.5) if tree else rng.uniform(4.0, 7.0)),
                            float(rng.uniform(1.2, 3.0)) if tree else 0.0,
                            np.array([rng.uniform(30, 80), rng.uniform(70, 140), rng.uniform(20, 60)]),
                            int(rng.integers(0, 2**31))))

    width, height = SIZES[int(rng.integers(0, len(SIZES)))]
    fov_long = float(rng.uniform(*FOV_RANGE))
    focal = focal_from_hfov(fov_long, max(width, height))
    pan = float(rng.choice([0.0, 180.0]) + rng.uniform(-35, 35)) if rng.uniform() < 0.5 else float(rng.uniform(-180, 180))
    pitch, roll = float(rng.uniform(*PITCH_RANGE)), float(rng.uniform(*ROLL_RANGE))
    rotation = rotation_from_angles(pan, pitch, roll).numpy()
    camera_height = float(rng.uniform(3.0, 8.0) if rng.uniform() < 0.2 else rng.uniform(1.3, 1.9))
    eye = np.array([rng.uniform(-road_half + 0.5, road_half - 0.5), -camera_height, 0.0])
    zenith = np.array([rng.uniform(60, 120), rng.uniform(110, 160), rng.uniform(190, 240)])
    haze = np.array([rng.uniform(190, 225), rng.uniform(195, 225), rng.uniform(200, 230)])
    return StreetScene(width, height, focal, rotation, eye, fov_long, pan, directions, curved_at >= 0, road_half, sidewalk,
                       objects, (haze, zenith), float(rng.uniform(2.0, 5.0)), int(rng.integers(0, 2**31)))


def _facade_style(rng: np.random.Generator) -> dict:
    floor = float(rng.uniform(2.9, 3.6))
    bay = float(rng.uniform(2.2, 4.0))
    return {"colour": rng.uniform(90, 220, 3) * rng.uniform(0.8, 1.0, 3), "glass": rng.uniform(20, 80, 3),
            "bay": bay, "floor": floor,
            "window": (bay * float(rng.uniform(0.35, 0.7)), floor * float(rng.uniform(0.35, 0.6)))}


def _block(rng, side: float, z0: float, setback: float, directions: list[float], unused: list[float]) -> Block:
    """A parallelogram block on side ``side`` (-1 left, +1 right) starting at ``z0`` along the street:
    its front edge's and depth edge's azimuths are two of ``directions``, the front within 60 deg of
    the street, the depth at least 30 deg from it; ``unused`` directions are taken first."""
    fronts = [a for a in directions if abs(math.cos(math.radians(a))) >= 0.5]
    depths = [a for a in directions if abs(math.sin(math.radians(a))) >= 0.5]
    want = unused.pop(0) if unused else None
    if want is not None and want in fronts and (want not in depths or rng.uniform() < 0.5):
        front = want
        depth = float(rng.choice([a for a in depths if a != front] or [90.0]))
    elif want is not None:
        depth = want
        front = float(rng.choice([a for a in fronts if a != depth] or [0.0]))
    else:
        front = 0.0 if rng.uniform() < 0.6 else float(rng.choice(fronts))
        depth = float(rng.choice([a for a in depths if a != front] or [90.0]))
    u, v = azimuth_vector(front)[[0, 2]], azimuth_vector(depth)[[0, 2]]
    u = u if u[1] > 0 else -u  # the front runs along +z
    v = v if v[0] * side > 0 else -v  # the depth runs away from the street
    length, deep = float(rng.uniform(10.0, 30.0)), float(rng.uniform(10.0, 20.0))
    corners = np.array([[0.0, 0.0], length * u, length * u + deep * v, deep * v])
    corners[:, 1] += z0 - corners[:, 1].min()
    near_x = corners[:, 0].min() if side > 0 else -corners[:, 0].max()
    corners[:, 0] += side * (setback + float(rng.uniform(0.0, 3.0)) - near_x)
    azimuths = np.array([front, depth, front, depth], dtype=np.float64)
    return Block(corners, float(rng.uniform(6.0, 30.0)), edge_azimuth=azimuths, **_facade_style(rng))


def _curved_block(rng, side: float, z0: float, setback: float) -> Block:
    """A block whose street facade is a circular arc (a circular segment footprint, bulging towards
    the street), facets of about 1.5 m."""
    radius = float(rng.uniform(10.0, 25.0))
    half = math.radians(float(rng.uniform(35.0, 70.0)))
    steps = max(6, int(math.ceil(2 * half * radius / 1.5)))
    theta = np.linspace(-half, half, steps + 1)
    arc = np.stack([-side * radius * np.cos(theta), radius * np.sin(theta)], 1)  # bulges towards the street
    arc[:, 1] += z0 - arc[:, 1].min()
    near_x = arc[:, 0].min() if side > 0 else -arc[:, 0].max()
    arc[:, 0] += side * (setback + float(rng.uniform(0.0, 2.0)) - near_x)
    footprint = arc  # closed by the chord from the last arc point back to the first
    azimuths = np.full(len(footprint), np.nan)
    azimuths[-1] = 0.0  # the chord runs along the street, at the back
    return Block(footprint, float(rng.uniform(8.0, 25.0)), edge_azimuth=azimuths, **_facade_style(rng))


# --------------------------------------------------------------------------- rendering

class _Painter:
    """Projects world polygons through the scene's camera and paints them on an RGB canvas."""

    def __init__(self, scene: StreetScene, canvas: np.ndarray):
        self.scene, self.canvas = scene, canvas
        self.K, self.R, self.eye = scene.K, scene.rotation, scene.eye

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> camera frame (..., 3)."""
        return (points - self.eye) @ self.R.T

    def project(self, cam: np.ndarray) -> np.ndarray:
        """Camera-frame points (..., 3) with z > 0 -> pixels (..., 2)."""
        uvw = cam @ self.K.T
        return uvw[..., :2] / uvw[..., 2:3]

    def polygons(self, polys: np.ndarray, colour, clip: bool = True) -> None:
        """Fill world polygons ``polys`` (P, M, 3) in one colour: those wholly in front of the camera
        as they are, those that cross the near plane clipped to it (when ``clip``)."""
        if len(polys) == 0:
            return
        cam = self.to_camera(polys)
        front = (cam[..., 2] >= NEAR).all(-1)
        pieces = list(self.project(cam[front]))
        if clip:
            for poly in cam[~front & (cam[..., 2] >= NEAR).any(-1)]:
                kept = _clip_near(poly)
                if len(kept) >= 3:
                    pieces.append(self.project(kept))
        pieces = [np.round(p * 16).astype(np.int32) for p in pieces if np.isfinite(p).all() and np.abs(p).max() < 1e7]
        if pieces:
            cv2.fillPoly(self.canvas, pieces, tuple(float(c) for c in np.clip(colour, 0, 255)), cv2.LINE_AA, shift=4)

    def visible(self, polys: np.ndarray) -> bool:
        """Whether any of the world polygons (P, M, 3) may reach the image (a cheap frustum test)."""
        cam = self.to_camera(polys.reshape(-1, 3))
        if (cam[:, 2] < NEAR).all():
            return False
        pix = self.project(cam[cam[:, 2] >= NEAR])
        behind = (cam[:, 2] < NEAR).any()
        w, h = self.scene.width, self.scene.height
        return bool(behind or ((pix[:, 0].max() >= 0) and (pix[:, 0].min() < w) and (pix[:, 1].max() >= 0)
                               and (pix[:, 1].min() < h)))


def _clip_near(poly: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman clip of a camera-frame polygon (M, 3) to ``z >= NEAR``."""
    out = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        ina, inb = a[2] >= NEAR, b[2] >= NEAR
        if ina:
            out.append(a)
        if ina != inb:
            t = (NEAR - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.asarray(out).reshape(-1, 3)


def _quads(p0: np.ndarray, p1: np.ndarray, s0: np.ndarray, s1: np.ndarray, y0: np.ndarray, y1: np.ndarray) -> np.ndarray:
    """Vertical world quads (P, 4, 3) on the facade from ``p0`` to ``p1`` ((x, z), metres): along it
    from fraction ``s0`` to ``s1``, from world ``y0`` to ``y1`` (arrays broadcast to P)."""
    s0, s1, y0, y1 = np.broadcast_arrays(*(np.asarray(v, np.float64) for v in (s0, s1, y0, y1)))
    a, b = p0 + s0.reshape(-1, 1) * (p1 - p0), p0 + s1.reshape(-1, 1) * (p1 - p0)
    y0, y1 = y0.reshape(-1), y1.reshape(-1)
    return np.stack([np.stack([a[:, 0], y0, a[:, 1]], -1), np.stack([b[:, 0], y0, b[:, 1]], -1),
                     np.stack([b[:, 0], y1, b[:, 1]], -1), np.stack([a[:, 0], y1, a[:, 1]], -1)], 1)


def _shade(colour: np.ndarray, normal: np.ndarray) -> np.ndarray:
    return colour * (0.55 + 0.45 * max(0.0, float(normal @ LIGHT)))


def _paint_block(painter: _Painter, block: Block, rng: np.random.Generator) -> None:
    eye = painter.eye[[0, 2]]
    centre = block.footprint.mean(0)
    top = -block.height
    for i, p0 in enumerate(block.footprint):
        p1 = block.footprint[(i + 1) % len(block.footprint)]
        edge = p1 - p0
        length = float(np.linalg.norm(edge))
        normal = np.array([edge[1], -edge[0]]) / max(length, 1e-9)
        mid = (p0 + p1) / 2
        normal = normal if normal @ (mid - centre) > 0 else -normal
        if normal @ (eye - mid) <= 0:
            continue  # back face
        wall = _quads(p0, p1, 0.0, 1.0, 0.0, top)
        if not painter.visible(wall):
            continue
        normal3 = np.array([normal[0], 0.0, normal[1]])
        painter.polygons(wall, _shade(block.colour, normal3))
        bays = int((length - 0.6) // block.bay)
        floors = int((block.height - 1.0) // block.floor)
        if bays >= 1 and floors >= 1:
            margin = (length - bays * block.bay) / 2
            centres = (margin + (np.arange(bays) + 0.5) * block.bay) / length
            half_w = block.window[0] / 2 / length
            s, f = np.meshgrid(centres, np.arange(1, floors), indexing="ij")
            base = -f * block.floor - 0.9
            glass = _shade(block.glass, normal3)
            lit = rng.uniform(size=s.shape) < 0.15
            painter.polygons(_quads(p0, p1, (s - half_w)[~lit], (s + half_w)[~lit], base[~lit],
                                    (base - block.window[1])[~lit]), glass)
            painter.polygons(_quads(p0, p1, (s - half_w)[lit], (s + half_w)[lit], base[lit],
                                    (base - block.window[1])[lit]), glass + 90)
            bands = -np.arange(1, floors + 1) * block.floor
            painter.polygons(_quads(p0, p1, 0.0, 1.0, bands, bands - 0.18), _shade(block.colour * 0.7, normal3))
            doors = centres[rng.uniform(size=len(centres)) < 0.3]
            painter.polygons(_quads(p0, p1, doors - 0.6 / length, doors + 0.6 / length, 0.0, -2.3),
                             _shade(block.glass * 0.8 + 20, normal3))
        painter.polygons(_quads(p0, p1, 0.0, 1.0, top, top + 0.5), _shade(block.colour * 0.6, normal3))


def _box_faces(centre: np.ndarray, azimuth: float, size: tuple[float, float, float], bottom: float) -> list[np.ndarray]:
    """The 5 visible-candidate faces (4, 3) of a box: ``size`` = (length, width, height) metres, the
    long axis at ``azimuth``, standing at world height ``bottom`` (y, down positive)."""
    u, v = azimuth_vector(azimuth)[[0, 2]], azimuth_vector(azimuth + 90.0)[[0, 2]]
    length, width, height = size
    corners = [centre + a * length / 2 * u + b * width / 2 * v for a, b in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    low = [np.array([c[0], bottom, c[1]]) for c in corners]
    high = [np.array([c[0], bottom - height, c[1]]) for c in corners]
    faces = [np.array([low[i], low[(i + 1) % 4], high[(i + 1) % 4], high[i]]) for i in range(4)]
    return faces + [np.array(high)]


def _paint_box(painter: _Painter, car: Box) -> None:
    eye_cam = painter.eye
    for size, bottom, colour, inset in (((4.3, 1.8, 0.8), -0.3, car.colour, 0.0),
                                        ((2.4, 1.6, 0.6), -1.1, car.colour * 0.4 + 30, -0.3)):
        centre = car.centre + inset * azimuth_vector(car.azimuth)[[0, 2]]
        faces = _box_faces(centre, car.azimuth, size, bottom)
        middle = np.mean([f.mean(0) for f in faces], 0)
        for face in faces:
            normal = face.mean(0) - middle
            if normal @ (eye_cam - face.mean(0)) > 0:
                painter.polygons(face[None], _shade(colour, normal / np.linalg.norm(normal)))
    for dx in (-1.4, 1.4):  # wheels: dark blobs at the car's sides
        c = car.centre + dx * azimuth_vector(car.azimuth)[[0, 2]]
        painter.polygons(np.array([_box_faces(c, car.azimuth, (0.7, 1.9, 0.5), 0.0)[4]]), np.array([25.0, 25, 25]))


def _paint_tree(painter: _Painter, tree: Tree) -> None:
    rng = np.random.default_rng(tree.seed)
    to_eye = painter.eye[[0, 2]] - tree.base
    side = np.array([to_eye[1], -to_eye[0]]) / max(np.linalg.norm(to_eye), 1e-9)
    half = 0.15 if tree.crown > 0 else 0.08
    trunk = np.array([[tree.base[0] - half * side[0], 0.0, tree.base[1] - half * side[1]],
                      [tree.base[0] + half * side[0], 0.0, tree.base[1] + half * side[1]],
                      [tree.base[0] + half * side[0], -tree.trunk, tree.base[1] + half * side[1]],
                      [tree.base[0] - half * side[0], -tree.trunk, tree.base[1] - half * side[1]]])
    painter.polygons(trunk[None], np.array([70.0, 55, 40]) if tree.crown > 0 else np.array([50.0, 50, 55]))
    if tree.crown <= 0:
        return
    centre = painter.to_camera(np.array([tree.base[0], -tree.trunk - tree.crown * 0.8, tree.base[1]]))
    if centre[2] < NEAR + tree.crown:
        return
    c = painter.project(centre)
    radius = painter.scene.focal_px * tree.crown / centre[2]
    if radius < 1.0 or radius > 4 * max(painter.scene.width, painter.scene.height):
        return
    for k in range(3):  # overlapping irregular blobs
        offset = rng.normal(0, radius * 0.3, 2)
        angles = np.sort(rng.uniform(0, 2 * np.pi, 18))
        r = radius * rng.uniform(0.55, 0.9, 18)
        blob = c + offset + np.stack([np.cos(angles), np.sin(angles)], 1) * r[:, None]
        cv2.fillPoly(painter.canvas, [np.round(blob * 16).astype(np.int32)],
                     tuple(float(v) for v in np.clip(tree.colour * (0.7 + 0.15 * k), 0, 255)), cv2.LINE_AA, shift=4)
    strokes = int(min(40, 6 + radius / 3))
    for _ in range(strokes):  # branches and leaf clusters: short edges at random angles
        p = c + rng.normal(0, radius * 0.45, 2)
        d = rng.normal(0, 1, 2)
        q = p + d / max(np.linalg.norm(d), 1e-9) * rng.uniform(0.1, 0.4) * radius
        cv2.line(painter.canvas, tuple(np.round(p * 16).astype(int)), tuple(np.round(q * 16).astype(int)),
                 tuple(float(v) for v in tree.colour * 0.35), max(1, int(radius / 40)), cv2.LINE_AA, shift=4)


def _background(scene: StreetScene) -> np.ndarray:
    """Sky and ground per pixel (H, W, 3) float RGB: the ray of each pixel centre; the ground
    ``y = 0`` with the road, lane marks, kerbs and paving, faded by distance into the haze."""
    w, h = scene.width, scene.height
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(scene.K).T @ scene.rotation  # world directions
    rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
    haze, zenith = scene.sky
    up = np.clip(-rays[..., 1], 0.0, 1.0)[..., None]
    image = haze + (zenith - haze) * np.sqrt(up)
    ground = rays[..., 1] > 1e-6
    t = -scene.eye[1] / rays[..., 1][ground]
    x = scene.eye[0] + t * rays[..., 0][ground]
    z = scene.eye[2] + t * rays[..., 2][ground]
    colour = np.full(t.shape + (3,), 85.0)
    road = np.abs(x) < scene.road_half
    colour[~road] = 150.0
    near = t < 60.0
    colour[road & near & (np.abs(x) < 0.08) & (np.mod(z, 9.0) < 4.5)] = 215.0
    colour[road & near & (np.abs(np.abs(x) - scene.road_half + 0.4) < 0.08)] = 200.0
    kerb = (np.abs(x) >= scene.road_half) & (np.abs(x) < scene.road_half + 0.25)
    colour[kerb] = 185.0
    joints = ~road & (t < 25.0) & (np.mod(np.abs(x) - scene.road_half, 1.2) < 0.05)
    if any(_angle_between(a, 90.0) < 1e-9 for a in scene.directions):
        joints |= ~road & (t < 25.0) & (np.mod(z, 1.2) < 0.05)
    colour[joints] -= 45.0
    fog = np.exp(-t / 140.0)[:, None]
    image[ground] = haze * (1 - fog) + colour * fog
    return image


def render(scene: StreetScene) -> np.ndarray:
    """The scene through its camera: (H, W, 3) uint8 RGB, pixel centres at integer coordinates
    (:mod:`fr_torch.core.geometry.conventions`); painter's order, farthest object first, then a
    slight blur and Gaussian noise."""
    canvas = _background(scene)
    painter = _Painter(scene, canvas)
    rng = np.random.default_rng(scene.render_seed)
    eye = scene.eye[[0, 2]]
    for item in sorted(scene.objects, key=lambda o: -o.key(eye)):
        if isinstance(item, Block):
            _paint_block(painter, item, rng)
        elif isinstance(item, Box):
            _paint_box(painter, item)
        else:
            _paint_tree(painter, item)
    canvas = cv2.GaussianBlur(canvas, (3, 3), 0.6)
    canvas += rng.normal(0.0, scene.noise_sigma, canvas.shape)
    return np.clip(canvas, 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- ground truth

def directions_in_view(scene: StreetScene, min_px: float = IN_VIEW_MIN_PX) -> list[float]:
    """The scene's directions whose straight facade outlines (the bottom and top edges of facades
    facing the camera, clipped to the near plane and the image) add up to at least ``min_px``
    pixels in the image; occlusion is ignored."""
    painter = _Painter(scene, np.zeros((1, 1, 3)))
    lengths = {a: 0.0 for a in scene.directions}
    eye = scene.eye[[0, 2]]
    for block in (o for o in scene.objects if isinstance(o, Block)):
        centre = block.footprint.mean(0)
        for i, p0 in enumerate(block.footprint):
            azimuth = block.edge_azimuth[i]
            p1 = block.footprint[(i + 1) % len(block.footprint)]
            mid = (p0 + p1) / 2
            normal = np.array([p1[1] - p0[1], p0[0] - p1[0]])
            normal = normal if normal @ (mid - centre) > 0 else -normal
            if np.isnan(azimuth) or normal @ (eye - mid) <= 0:
                continue
            for y in (0.0, -block.height):
                cam = clip_segment_near(*painter.to_camera(np.array([[p0[0], y, p0[1]], [p1[0], y, p1[1]]])), NEAR)
                if cam is None:
                    continue
                a, b = clip_segment(*painter.project(cam), scene.width - 1, scene.height - 1)
                if a is not None:
                    key = min(lengths, key=lambda d: _angle_between(d, azimuth))
                    lengths[key] += float(np.linalg.norm(b - a))
    return [a for a in scene.directions if lengths[a] >= min_px]


def ground_truth_row(scene: StreetScene, split: str, index: int, file: str) -> dict:
    """One ``gt.csv`` row (:data:`GT_COLUMNS` + :data:`EXTRA_COLUMNS`) of scene ``index`` of ``split``."""
    import torch

    hz = horizon_angles(torch.as_tensor(scene.rotation))
    name = Path(file).stem
    cx, cy = (scene.width - 1) / 2.0, (scene.height - 1) / 2.0
    in_view = directions_in_view(scene)
    row = {"file": file, "pano": name, "group": name, "split": split, "width": scene.width, "height": scene.height,
           "cx": cx, "cy": cy, "focal_px": scene.focal_px, "hfov_deg": hfov_from_focal(scene.focal_px, scene.width),
           "pan_deg": scene.pan_deg, "tilt_deg": float(hz["tilt_deg"]), "roll_deg": float(hz["roll_deg"]),
           "pitch_deg": float(hz["pitch_deg"]), "manhattan_known": False, "manhattan_yaw_deg": 0.0,
           "scene": SPLIT_OFFSETS[split] + index, "n_directions": len(scene.directions),
           "directions_deg": ";".join(f"{a:.4f}" for a in scene.directions), "n_directions_in_view": len(in_view),
           "directions_in_view_deg": ";".join(f"{a:.4f}" for a in in_view), "curved": scene.curved,
           "fov_long_deg": scene.fov_long_deg, "camera_height_m": -float(scene.eye[1])}
    row.update({c: float(v) for c, v in zip(R_COLUMNS, scene.rotation.reshape(-1).tolist())})
    return row


# --------------------------------------------------------------------------- the dataset

def write_dataset(out: str | Path, seed: int = 0, counts: dict[str, int] | None = None,
                  quiet: bool = False) -> dict:
    """Render ``counts`` scenes per split (default 200 train, 200 test) into ``out``: images,
    ``gt.csv``, ``contact_sheet.png``; returns the summary written to ``dataset.json``."""
    counts = {"train": 200, "test": 200} if counts is None else counts
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows, sheet, captions = [], [], []
    for split, count in counts.items():
        for i in range(count):
            scene = sample_scene(seed, SPLIT_OFFSETS[split] + i)
            image = render(scene)
            file = f"images/{split}_{i:04d}.jpg"
            save_rgb(out / file, image)
            row = ground_truth_row(scene, split, i, file)
            rows.append(row)
            if len(sheet) < 15 and i < 8:
                sheet.append(cv2.resize(image, (400, 400 * scene.height // scene.width)))
                captions.append(f"{Path(file).stem}  FOV {scene.fov_long_deg:.0f} (long)  tilt {row['tilt_deg']:+.1f}"
                                f"\nroll {row['roll_deg']:+.1f}  {row['n_directions']} directions"
                                + ("  curved" if scene.curved else ""))
    gt = pd.DataFrame(rows, columns=GT_COLUMNS + EXTRA_COLUMNS)
    gt.to_csv(out / "gt.csv", index=False, float_format="%.10g")
    contact_sheet(sheet, captions, out / "contact_sheet.png")
    summary = {
        "generator": "fr_eval.datasets.synthetic_streets", "seed": int(seed), "counts": dict(counts),
        "scene_index": {s: [SPLIT_OFFSETS[s], SPLIT_OFFSETS[s] + n] for s, n in counts.items()},
        "sizes": [list(s) for s in SIZES], "fov_long_range_deg": list(FOV_RANGE),
        "pitch_range_deg": list(PITCH_RANGE), "roll_range_deg": list(ROLL_RANGE),
        "principal_point": "the image centre ((w-1)/2, (h-1)/2) (gt.csv cx, cy)",
        "rotation": "world->camera in the street frame (z along the street, y down); R.T = Ry(pan) Rx(pitch) Rz(roll)",
        "directions": {str(n): int((gt["n_directions"] == n).sum()) for n in (2, 3, 4)},
        "curved": int(gt["curved"].sum()),
        "seconds": round(time.perf_counter() - t0, 1),
    }
    (out / "dataset.json").write_text(json.dumps(summary, indent=2))
    if not quiet:
        print(f"wrote {len(gt)} views ({', '.join(f'{s}: {n}' for s, n in counts.items())}) to {out} "
              f"in {summary['seconds']} s")
    return summary


def _directions(text) -> tuple[float, ...]:
    return tuple(float(a) for a in str(text).split(";") if a and a != "nan")


@register_dataset(NAME)
def load_synthetic_streets(root=None, split: str = "test", path=None, **kwargs) -> list[CalibrationSample]:
    """The views of ``<cache_root>/synthetic-streets`` (``path=``, or ``root`` holding a ``gt.csv``,
    for another folder); split ``train``, ``test`` or ``all``.  Each sample's camera has
    ``pan_known=False`` (module docstring); ``extra`` adds ``n_directions``, ``directions_deg``,
    ``n_directions_in_view``, ``directions_in_view_deg`` (tuples of azimuths, degrees), ``curved``."""
    folder = dataset_folder(root, path, NAME)
    if not (folder / "gt.csv").is_file():
        raise FileNotFoundError(f"{folder / 'gt.csv'} not found: generate it with "
                                f"`python -m fr_eval.datasets.synthetic_streets --out {folder}`")
    views = PanoViews(folder, split)
    samples = views.samples(**kwargs)
    for sample, (_, row) in zip(samples, views.table.iterrows()):
        sample.extra.update({"n_directions": int(row["n_directions"]),
                             "directions_deg": _directions(row["directions_deg"]),
                             "n_directions_in_view": int(row["n_directions_in_view"]),
                             "directions_in_view_deg": _directions(row["directions_in_view_deg"]),
                             "curved": bool(row["curved"])})
    return samples


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m fr_eval.datasets.synthetic_streets",
                                     description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=None, help=f"output folder (default <$FR_CACHE>/{NAME})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--train", type=int, default=200, help="training scenes (default 200)")
    parser.add_argument("--test", type=int, default=200, help="test scenes (default 200)")
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.train < 0 or args.test < 0:
        parser.error("--train and --test take a count >= 0")
    from fr_eval.paths import cache_root

    out = args.out if args.out is not None else cache_root() / NAME
    summary = write_dataset(out, args.seed, {"train": args.train, "test": args.test}, quiet=args.quiet)
    summary["command"] = "python -m fr_eval.datasets.synthetic_streets " + " ".join(
        argv if argv is not None else sys.argv[1:])
    (out / "dataset.json").write_text(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
