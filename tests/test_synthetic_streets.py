"""fr_eval.datasets.synthetic_streets: deterministic scenes whose drawn edges meet at the camera's
vanishing points and horizon; the loader and the harness read the generated folder."""
import numpy as np
import pytest

from fr_eval.datasets.registry import CalibrationSample, load_dataset
from fr_eval.datasets.synthetic_streets import (
    Block,
    azimuth_vector,
    render,
    sample_scene,
    scene_directions,
    write_dataset,
)
from fr_eval.scoring.horizon_metric import FRAME, truth_horizons
from fr_torch.core.geometry.camera import Camera
from fr_torch.core.geometry.horizon import Horizon


def _line_through(K, R, eye, p, q):
    """Image line (3,) through the projections of world points p, q (3,)."""
    a, b = (K @ (R @ (x - eye)) for x in (p, q))
    return np.cross(a, b)


def _meets(line, point) -> float:
    """Sine-like incidence of a homogeneous line and point (0 = the point lies on the line)."""
    return abs(line @ point) / (np.linalg.norm(line[:2]) * np.linalg.norm(point))


def test_scenes_are_deterministic_by_seed_and_index():
    a, b, c = sample_scene(3, 7), sample_scene(3, 7), sample_scene(3, 8)
    np.testing.assert_array_equal(render(a), render(b))
    assert a.directions == b.directions and not np.array_equal(a.rotation, c.rotation)


def test_directions_are_several_and_not_all_orthogonal():
    rng = np.random.default_rng(0)
    for _ in range(50):
        d = scene_directions(rng)
        assert 2 <= len(d) <= 4 and d[0] == 0.0
        off = [min(a % 90.0, 90.0 - a % 90.0) for a in d]
        assert max(off) >= 12.0 - 1e-9  # one direction at least 12 deg from the street's right angles


@pytest.mark.parametrize("index", [0, 1, 2, 5])
def test_edges_meet_at_the_cameras_vanishing_points_on_its_horizon(index):
    scene = sample_scene(0, index)
    K, R, eye = scene.K, scene.rotation, scene.eye
    vertical = K @ R[:, 1]
    horizon = Horizon.from_camera(Camera(scene.width, scene.height, scene.focal_px, None, R)).line
    blocks = [o for o in scene.objects if isinstance(o, Block)]
    used = set()
    for block in blocks:
        for i, (x, z) in enumerate(block.footprint):
            # a vertical corner edge meets the vertical VP
            assert _meets(_line_through(K, R, eye, np.array([x, 0.0, z]), np.array([x, -block.height, z])),
                          vertical) < 1e-9
            azimuth = block.edge_azimuth[i]
            if np.isnan(azimuth):
                continue
            used.add(float(azimuth))
            x1, z1 = block.footprint[(i + 1) % len(block.footprint)]
            vp = K @ R @ azimuth_vector(azimuth)
            assert _meets(horizon, vp) < 1e-9  # every horizontal direction's VP lies on the horizon
            for y in (0.0, -block.height):  # the footprint edge at the ground and the roof meets it
                assert _meets(_line_through(K, R, eye, np.array([x, y, z]), np.array([x1, y, z1])), vp) < 1e-9
    assert used == set(scene.directions)  # every direction of the scene is a building edge


def test_the_loader_gives_samples_the_harness_scores(tmp_path):
    write_dataset(tmp_path, seed=1, counts={"train": 1, "test": 2}, quiet=True)
    samples = load_dataset("synthetic-streets", root=tmp_path, split="test")
    assert len(samples) == 2 and len(load_dataset("synthetic-streets", root=tmp_path, split="all")) == 3
    for i, sample in enumerate(samples):
        scene = sample_scene(1, 1_000_000 + i)
        assert isinstance(sample, CalibrationSample) and sample.image_path.is_file() and sample.split == "test"
        assert (sample.width, sample.height) == (scene.width, scene.height)
        assert sample.focal_px == pytest.approx(scene.focal_px) and sample.camera.pan_known is False
        np.testing.assert_allclose(sample.camera.rotation, scene.rotation, atol=1e-9)
        assert sample.principal_point == ((scene.width - 1) / 2, (scene.height - 1) / 2)
        assert sample.extra["n_directions"] == len(scene.directions)
        assert sample.extra["directions_deg"] == pytest.approx(scene.directions, abs=1e-4)
        assert set(truth_horizons(sample)) == {FRAME}
    with pytest.raises(FileNotFoundError, match="synthetic_streets"):
        load_dataset("synthetic-streets", root=tmp_path / "missing", split="test", path=tmp_path / "missing")


def test_fr_eval_runs_on_two_generated_views(tmp_path):
    from fr_eval.protocols.eval_command import main

    write_dataset(tmp_path / "data", seed=2, counts={"train": 0, "test": 2}, quiet=True)
    common = ["--dataset", "synthetic-streets", "--split", "test", "--data-root", str(tmp_path / "data"),
              "--methods", "fast-fr", "--no-plots"]
    assert main(["--task", "horizon", *common, "--out", str(tmp_path / "horizon")]) == 0
    assert "AUC (frame)" in (tmp_path / "horizon" / "horizon_summary.md").read_text()
    assert main([*common, "--out", str(tmp_path / "camera")]) == 0
    assert (tmp_path / "camera" / "predictions.csv").is_file()
