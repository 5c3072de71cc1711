"""Triangulation's memory grows with the number of (point, camera) observations, not with
cameras squared, and a reconstruction of more observations than its bound is refused before
anything is allocated. (The full command's peak memory against the number of cameras is
benchmarks/triangulate_memory.py.)"""

from __future__ import annotations

import tracemalloc

import numpy as np
from helpers import one_line_error, run

import mvtex
from mvtex.data.camera import look_at


def ring(count: int) -> list:
    """`count` 64x64 cameras on a circle of radius 1.5 m around the origin, looking at it."""
    return [look_at(f"c{i:03d}", (1.5 * np.sin(a), 0.2 * np.sin(5 * a), 1.5 * np.cos(a)), (0, 0, 0), width=64,
                    height=64, focal=60.0) for i, a in enumerate(np.linspace(0, 2 * np.pi, count, endpoint=False))]


def test_many_cameras_triangulate_in_memory_linear_in_the_observations():
    cameras = ring(200)
    truth = np.random.default_rng(0).uniform(-0.2, 0.2, (100, 3))
    pixels = np.stack([cam.project(truth)[0] for cam in cameras], axis=1)  # (100,200,2): the exact projections
    tracemalloc.start()
    try:
        points = mvtex.triangulate_points(cameras, pixels, np.ones((100, 200)))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    np.testing.assert_allclose(points, truth, atol=1e-9)
    # 20,000 observations: a few hundred bytes each is ~10 MB. A full SVD of the DLT rows
    # (U: 400x400 per point) or every camera pair at once (200x200 per point) is > 100 MB.
    assert peak < 40e6, peak


def test_a_reconstruction_beyond_the_observation_bound_is_refused_before_it_starts(
        tmp_path, tiny_dataset, rig_file, slid_sheet0, capsys, monkeypatch):
    import mvtex.recon.options

    vertices = mvtex.load_dataset(tiny_dataset).num_vertices
    monkeypatch.setattr(mvtex.recon.options, "MAX_OBSERVATIONS", 2 * vertices - 1)  # two cameras are one too many

    def no_work(*args, **kwargs):
        raise AssertionError("the reconstruction started")

    monkeypatch.setattr("mvtex.recon.triangulate.collect_hypotheses", no_work)
    code, _, err = run(capsys, "triangulate", tiny_dataset, "--rig", rig_file, "--texcoords", slid_sheet0, "--pose", 0,
                       "--out", tmp_path / "rec", "--quiet")
    one_line_error(code, err, slid_sheet0, f"{2 * vertices} observations", "fewer cameras")
    assert not (tmp_path / "rec").exists()
