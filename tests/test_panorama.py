"""Panorama -> pinhole view generator (fr_eval.datasets.panorama, fr_eval.datasets.make_dataset, fr_eval.datasets.panoviews).

The central check renders views from a synthetic equirectangular panorama whose pixels *encode
their own viewing direction* (channels = unit ray of the pixel centre in the pano frame).  A view
pixel (u, v) must then show the direction ``Ry(yaw) R.T K^-1 (u, v, 1)`` exactly (up to bilinear
interpolation of a smooth field, ~1e-4 deg), so any half-pixel slip of the panorama or view grid,
a wrong seam / pole treatment, a sign flip of pan / pitch / roll / yaw or a wrong principal point
is caught.  From the same renderings the horizon and the vanishing points are located in the
image and compared with ``K R`` to sub-pixel accuracy.
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch

from fr_eval.datasets import make_dataset
from fr_eval.datasets.panorama import (
    cube_face_rotations,
    cubemap_to_equirect,
    direction_from_lonlat,
    equirect_pixel_from_direction,
    lonlat_from_direction,
    render_views,
    save_rgb,
    yaw_rotation,
)
from fr_torch.core.geometry.conventions import (
    focal_from_hfov,
    horizon_angles,
    image_centre,
    intrinsics,
    rotation_from_angles,
)

PANO_W, PANO_H = 1024, 512
VIEW = (160, 120)
FOVS = (60.0, 75.0, 90.0, 105.0, 120.0)


def direction_pano(width=PANO_W, height=PANO_H) -> torch.Tensor:
    """(3, H, W) float panorama whose pixel values are the unit directions of the pixel centres."""
    lon = ((torch.arange(width, dtype=torch.float64) + 0.5) / width - 0.5) * 2 * math.pi
    lat = (0.5 - (torch.arange(height, dtype=torch.float64) + 0.5) / height) * math.pi
    la, lo = torch.meshgrid(lat, lon, indexing="ij")
    return direction_from_lonlat(lo, la).permute(2, 0, 1).float()


@pytest.fixture(scope="module")
def dpano() -> torch.Tensor:
    return direction_pano()


def expected_rays(R, f, size, yaw) -> torch.Tensor:
    """Analytic pano-frame unit rays (h, w, 3) of the view pixel centres: Ry(yaw) R^T K^-1 (u, v, 1)."""
    w, h = size
    K = intrinsics(torch.tensor(f, dtype=torch.float64), torch.tensor(image_centre(w, h), dtype=torch.float64))
    vs, us = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    pix = torch.stack([us, vs, torch.ones_like(us)], -1)
    M = yaw_rotation(yaw) @ R.T @ torch.linalg.inv(K)
    d = pix @ M.T
    return d / d.norm(dim=-1, keepdim=True)


def rendered_rays(dpano, R, f, size, yaw, mode="bilinear") -> torch.Tensor:
    out = render_views(dpano, R[None], torch.tensor([f]), size=size, manhattan_yaw_deg=yaw, mode=mode)
    d = out[0].permute(1, 2, 0).double()
    return d / d.norm(dim=-1, keepdim=True)


def angle_deg(a, b) -> torch.Tensor:
    return torch.rad2deg(torch.atan2(torch.cross(a, b, dim=-1).norm(dim=-1), (a * b).sum(-1)))


# (pan, pitch, roll, yaw): nonzero everything, one view across the +-180 seam, one over the zenith
VIEWS = [(37.0, 21.0, 7.5, 23.0), (-128.0, -17.0, -9.0, -61.0), (178.0, 12.0, 4.0, 0.0)]


@pytest.mark.parametrize("hfov", FOVS)
def test_view_pixels_sample_the_analytic_ray(dpano, hfov):
    f = focal_from_hfov(hfov, VIEW[0])
    for pan, pitch, roll, yaw in VIEWS:
        R = rotation_from_angles(pan, pitch, roll)
        err = angle_deg(rendered_rays(dpano, R, f, VIEW, yaw), expected_rays(R, f, VIEW, yaw))
        assert float(err.max()) < 0.001, (hfov, pan, pitch, roll, float(err.max()))


def test_pole_seam_and_bicubic(dpano):
    f = focal_from_hfov(90.0, VIEW[0])
    R = rotation_from_angles(-170.0, 84.0, 6.0)  # straddles the zenith and the seam
    # bilinear reproduces the smooth field to ~1e-4 deg; PyTorch's bicubic kernel (a = -0.75) does
    # not reproduce linear ramps (up to 0.05 px wobble), i.e. ~0.025 deg on this coarse panorama
    for mode, tol in (("bilinear", 0.001), ("bicubic", 0.03)):
        err = angle_deg(rendered_rays(dpano, R, f, VIEW, 10.0, mode), expected_rays(R, f, VIEW, 10.0))
        assert float(err.max()) < tol, (mode, float(err.max()))
    # looking straight up: the principal point ray is the zenith itself, sampled across the pole
    R = rotation_from_angles(33.0, 90.0, 0.0)
    err = angle_deg(rendered_rays(dpano, R, f, VIEW, 0.0), expected_rays(R, f, VIEW, 0.0))
    assert float(err.max()) < 0.001, float(err.max())


def test_half_pixel_offsets_would_be_detected(dpano):
    """The check above is sensitive enough: a principal point at (w/2, h/2), half a pixel off the image
    centre, fails it."""
    w, h = VIEW
    f = focal_from_hfov(60.0, w)
    R = rotation_from_angles(20.0, 10.0, 5.0)
    got = rendered_rays(dpano, R, f, VIEW, 0.0)
    K = intrinsics(torch.tensor(f, dtype=torch.float64), torch.tensor([w / 2.0, h / 2.0], dtype=torch.float64))
    vs, us = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    d = torch.stack([us, vs, torch.ones_like(us)], -1) @ (R.T @ torch.linalg.inv(K)).T
    wrong = d / d.norm(dim=-1, keepdim=True)
    assert float(angle_deg(got, wrong).min()) > 0.1


def _horizon_rows(d_room: torch.Tensor) -> torch.Tensor:
    """Per column, the sub-pixel row where the room-frame y component changes sign (nan if none)."""
    y = d_room[..., 1]  # (h, w)
    rows = torch.full((y.shape[1],), float("nan"), dtype=torch.float64)
    for c in range(y.shape[1]):
        s = torch.nonzero((y[:-1, c] * y[1:, c]) <= 0).ravel()
        if len(s):
            r = int(s[0])
            rows[c] = r + y[r, c] / (y[r, c] - y[r + 1, c])
    return rows


def _locate_vp(d_room: torch.Tensor, axis: int, guess: torch.Tensor) -> torch.Tensor:
    """Sub-pixel image point where the rendered ray is parallel to room axis ``axis`` (affine fit)."""
    others = [i for i in range(3) if i != axis]
    u0, v0 = int(round(float(guess[0]))), int(round(float(guess[1])))
    us, vs, t0, t1 = [], [], [], []
    for dv in range(-2, 3):
        for du in range(-2, 3):
            d = d_room[v0 + dv, u0 + du]
            us.append(u0 + du)
            vs.append(v0 + dv)
            t0.append(d[others[0]] / d[axis])
            t1.append(d[others[1]] / d[axis])
    A = torch.stack([torch.tensor(us, dtype=torch.float64), torch.tensor(vs, dtype=torch.float64),
                     torch.ones(len(us), dtype=torch.float64)], 1)
    c0 = torch.linalg.lstsq(A, torch.stack(t0).double()[:, None]).solution.ravel()
    c1 = torch.linalg.lstsq(A, torch.stack(t1).double()[:, None]).solution.ravel()
    M = torch.stack([c0[:2], c1[:2]])
    return torch.linalg.solve(M, -torch.stack([c0[2], c1[2]]))


@pytest.mark.parametrize("hfov", FOVS)
def test_horizon_and_vanishing_points_match_K_R(dpano, hfov):
    w, h = 320, 240
    f = focal_from_hfov(hfov, w)
    K = intrinsics(torch.tensor(f, dtype=torch.float64), torch.tensor(image_centre(w, h), dtype=torch.float64))
    yaw = 31.0
    # pan 12: the room z axis' VP is inside the image; pitch -6 / roll 8 keep the horizon inside
    R = rotation_from_angles(12.0, -6.0, 8.0)
    d_pano = rendered_rays(dpano, R, f, (w, h), yaw)
    d_room = d_pano @ yaw_rotation(yaw)  # row vectors: d_room = Ry(yaw)^T d_pano
    # horizon: image line l = K^-T R[:, 1]
    line = torch.linalg.inv(K).T @ R[:, 1]
    cols = torch.arange(w, dtype=torch.float64)
    predicted = -(line[0] * cols + line[2]) / line[1]
    measured = _horizon_rows(d_room)
    ok = ~torch.isnan(measured)
    assert ok.sum() > 0.9 * w
    assert float((measured[ok] - predicted[ok]).abs().max()) < 0.05
    # vanishing point of room axis z (and of the vertical when it is in the image)
    vp = K @ R[:, 2]
    vp = vp[:2] / vp[2]
    found = _locate_vp(d_room, 2, vp)
    assert float((found - vp).norm()) < 0.05, (found, vp)
    # positive roll: the horizon rises to the right (scene rotated anticlockwise on screen)
    assert float(predicted[-1]) < float(predicted[0])
    assert float(measured[ok][-1]) < float(measured[ok][0])


def test_vertical_vanishing_point_for_steep_pitch(dpano):
    w, h = 320, 240
    f = focal_from_hfov(120.0, w)
    K = intrinsics(torch.tensor(f, dtype=torch.float64), torch.tensor(image_centre(w, h), dtype=torch.float64))
    R = rotation_from_angles(-40.0, -62.0, -7.0)  # looking steeply down: nadir VP inside the image
    d_room = rendered_rays(dpano, R, f, (w, h), -15.0) @ yaw_rotation(-15.0)
    vp = K @ R[:, 1]
    vp = vp[:2] / vp[2]
    assert 2 < vp[0] < w - 3 and 2 < vp[1] < h - 3
    found = _locate_vp(d_room, 1, vp)
    assert float((found - vp).norm()) < 0.05


def test_signs_pitch_up_sees_upper_half():
    """uint8 path: sky-white upper hemisphere, black lower; check pitch and roll signs."""
    pano = np.zeros((256, 512, 3), np.uint8)
    pano[:128] = 255
    w, h = 64, 48
    f = focal_from_hfov(60.0, w)
    R = rotation_from_angles(torch.tensor([50.0, 50.0, -120.0]), torch.tensor([20.0, -20.0, 0.0]),
                             torch.tensor([0.0, 0.0, 8.0]))
    views = render_views(pano, R, torch.full((3,), f), size=(w, h), manhattan_yaw_deg=17.0)
    assert views.shape == (3, h, w, 3) and views.dtype == np.uint8
    assert views[0, h // 2, w // 2, 0] == 255  # positive pitch looks up (sky)
    assert views[1, h // 2, w // 2, 0] == 0  # negative pitch looks down
    hz = horizon_angles(R)
    assert float(hz["tilt_deg"][0]) > 0 > float(hz["tilt_deg"][1])
    # positive roll: horizon higher (smaller row) on the right than on the left
    col_white = (views[2, :, :, 0] > 127).sum(0)  # rows of sky per column
    assert col_white[-2] < col_white[1]
    assert float(hz["roll_deg"][2]) > 0


def test_cubemap_to_equirect_matches_analytic_directions():
    S = 64
    R = cube_face_rotations()
    c = (torch.arange(S, dtype=torch.float64) + 0.5) / S * 2 - 1  # pixel edges at +-1
    yy, xx = torch.meshgrid(c, c, indexing="ij")
    cam = torch.stack([xx, yy, torch.ones_like(xx)], -1)
    faces = []
    for k in range(6):
        d = cam @ R[k]  # world = R^T cam  (row vectors)
        faces.append((d / d.norm(dim=-1, keepdim=True)).permute(2, 0, 1))
    faces = torch.stack(faces).float()
    eq = cubemap_to_equirect(faces, width=256)
    assert eq.shape == (3, 128, 256)
    truth = direction_pano(256, 128).double()
    got = eq.double() / eq.double().norm(dim=0, keepdim=True)
    err = angle_deg(got.permute(1, 2, 0), truth.permute(1, 2, 0))
    assert float(err.max()) < 0.05


def test_equirect_pixel_convention():
    d = direction_from_lonlat(torch.tensor([0.0, math.pi / 2, -math.pi + 1e-9], dtype=torch.float64),
                              torch.tensor([0.0, 0.0, math.pi / 2 - 1e-9], dtype=torch.float64))
    uv = equirect_pixel_from_direction(d, 2048, 1024)
    assert torch.allclose(uv[0], torch.tensor([1023.5, 511.5], dtype=torch.float64))  # centre: lon 0, horizon
    assert torch.allclose(uv[1], torch.tensor([1535.5, 511.5], dtype=torch.float64))  # x axis: right of centre
    assert torch.allclose(uv[2], torch.tensor([-0.5, -0.5], dtype=torch.float64), atol=1e-5)  # left / top edges
    # manhattan yaw: Ry(yaw) e_z lies at longitude +yaw (to the right)
    lon, _ = lonlat_from_direction(yaw_rotation(30.0) @ torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    assert math.degrees(float(lon)) == pytest.approx(30.0)
    # ZInD column -> yaw: the centre column is theta = 0, growing to the right
    assert make_dataset.zind_yaw_from_u(2047 / 2) == pytest.approx(0.0)
    assert make_dataset.zind_yaw_from_u(2047 * 0.75) == pytest.approx(90.0)


# --------------------------------------------------------------------------- generated datasets

def _tiny_panos(folder):
    folder.mkdir()
    rng = np.random.default_rng(0)
    names = []
    for i in range(6):
        img = rng.integers(0, 255, (64, 128, 3), dtype=np.uint8)
        name = f"pano_{i}"
        save_rgb(folder / f"{name}.png", img)
        names.append(name)
    # yaw table: pano_5 is not Manhattan; pano_0 and pano_1 are one room
    pd.DataFrame({"pano": names, "manhattan_yaw_deg": [0, 10, 20, 30, 40, 50],
                  "manhattan": [True] * 5 + [False],
                  "group": ["room_a", "room_a", "b", "c", "d", "e"]}).to_csv(folder.parent / "yaw.csv", index=False)
    return names


def _make(folder, out, seed, *extra):
    argv = ["--panoramas", str(folder), "--out", str(out), "--seed", str(seed), "--size", "48x32",
            "--views-per-pano", "5", "--yaw-csv", str(folder.parent / "yaw.csv"), "--quiet", "--sheet-views", "3", *extra]
    assert make_dataset.main(argv) == 0
    return pd.read_csv(out / "gt.csv")


def test_generated_dataset_split_and_reproducibility(tmp_path):
    folder = tmp_path / "panos"
    _tiny_panos(folder)
    a = _make(folder, tmp_path / "a", 3)
    b = _make(folder, tmp_path / "b", 3)
    c = _make(folder, tmp_path / "c", 4)
    pd.testing.assert_frame_equal(a, b)
    for f in a["file"]:
        assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes()
    assert not np.allclose(a["pan_deg"], c["pan_deg"])
    assert "pano_5" not in set(a["pano"])  # non-Manhattan excluded
    assert len(a) == 5 * 5 and sorted(a["hfov_deg"].unique()) == list(FOVS)
    # split by panorama group: every pano / group lies in exactly one split; same room together
    assert (a.groupby("pano")["split"].nunique() == 1).all()
    assert (a.groupby("group")["split"].nunique() == 1).all()
    assert set(a["split"]) == {"train", "test"}
    n_test = a.loc[a["split"] == "test", "pano"].nunique()
    assert a["group"].nunique() == 4 and n_test in (2, 3)  # 5 panos, test fraction 0.5
    # angles: ranges and the stored tilt / roll / pitch are those of horizon_angles(R)
    R = torch.as_tensor(a[make_dataset.R_COLUMNS].to_numpy().reshape(-1, 3, 3))
    hz = horizon_angles(R)
    for k in ("tilt_deg", "roll_deg", "pitch_deg"):
        assert np.allclose(a[k], hz[k].numpy(), atol=1e-6)
    assert a["pitch_deg"].abs().max() <= 30 and a["roll_deg"].abs().max() <= 10
    assert np.allclose(a["focal_px"], 24 / np.tan(np.radians(a["hfov_deg"]) / 2))
    assert a["manhattan_known"].all()
    assert (tmp_path / "a" / "contact_sheet.png").is_file() and (tmp_path / "a" / "dataset.json").is_file()
    # the loader
    from fr_eval.datasets.panoviews import PanoViews, load_panoviews

    test = load_panoviews(split="test", path=tmp_path / "a")
    assert len(test) == (a["split"] == "test").sum()
    assert len(PanoViews(tmp_path / "a", "all")) == len(a)
    s = test[0]
    row = a[a["file"].str.contains(s.name)].iloc[0]
    assert s.image_path.is_file() and s.principal_point == (23.5, 15.5) == image_centre(48, 32)
    assert (a["cx"] == 23.5).all() and (a["cy"] == 15.5).all()
    assert np.allclose(s.rotation, row[make_dataset.R_COLUMNS].to_numpy(float).reshape(3, 3))
    assert s.tilt_deg == pytest.approx(row["tilt_deg"]) and s.split == "test"
    # a gt.csv without the principal point's columns: the views were rendered at (w / 2, h / 2)
    a.drop(columns=["cx", "cy"]).to_csv(tmp_path / "a" / "gt.csv", index=False)
    assert PanoViews(tmp_path / "a", "all")[0].principal_point == (24.0, 16.0)
