"""What many tests share: closed-form meshes (no mvtex code involved, so tests can compare
mvtex against independent computations), running the command line, and a failure switch."""

from __future__ import annotations

import json
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np


def grid_mesh(nx: int = 24, ny: int = 20, size: float = 0.6):
    """A flat (nx x ny)-vertex sheet in the z=0 plane, CCW seen from +z, uv = normalised xy.

    Returns faces (m,3) int32, uv (n,2) float32, rest (n,3) float64.
    """
    xs = np.linspace(-size / 2, size / 2, nx)
    ys = np.linspace(-size / 2, size / 2, ny)
    X, Y = np.meshgrid(xs, ys)
    rest = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], axis=1)
    uv = ((rest[:, :2] + size / 2) / size).astype(np.float32)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    return faces, uv, rest


def wave(rest: np.ndarray, amplitude: float, phase: float, wavelength: float = 0.15) -> np.ndarray:
    """Fold the sheet along x with a sinusoid in z (a closed form)."""
    out = rest.copy()
    out[:, 2] = amplitude * np.sin(2 * np.pi * rest[:, 0] / wavelength + phase) + 0.3 * amplitude * np.cos(
        2 * np.pi * rest[:, 1] / (1.7 * wavelength))
    return out


def run(capsys, *argv) -> tuple[int, str, str]:
    """`mvtex.cli.main` on argv (anything str() turns into an argument): (exit code, stdout, stderr)."""
    from mvtex.cli import main

    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def run_json(capsys, *argv) -> dict:
    """`run` with --json: the one JSON object the command prints on stdout (exit code 0)."""
    code, out, err = run(capsys, *argv, "--json")
    assert code == 0, err
    lines = out.strip().splitlines()
    assert len(lines) == 1, out  # exactly one JSON object on stdout
    result = json.loads(lines[0])
    assert isinstance(result, dict)
    return result


def one_line_error(code: int, err: str, *needles) -> str:
    """Assert exit code 2 with exactly one error line naming every needle; returns the line."""
    assert code == 2, err
    lines = [line for line in err.strip().splitlines() if line.startswith(("mvtex ", "mvtex:"))]
    assert len(lines) == 1 and "Traceback" not in err, err
    for needle in needles:
        assert str(needle) in lines[0], lines[0]
    return lines[0]


def fail_slide_pose(monkeypatch, first_failure: int, error: BaseException) -> dict:
    """Make `mvtex.sliding.dataset.slide_pose` raise `error` from its `first_failure`-th call on
    (1-based). Returns the call counter {"n": calls so far}; lowering it postpones failures."""
    import mvtex.sliding.dataset as jobs

    original = jobs.slide_pose
    calls = {"n": 0}

    def failing(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] >= first_failure:
            raise error
        return original(*args, **kwargs)

    monkeypatch.setattr(jobs, "slide_pose", failing)
    return calls


def write_obj(path, positions, uv, faces):
    lines = [f"v {x:.9f} {y:.9f} {z:.9f}" for x, y, z in positions]
    lines += [f"vt {u:.9f} {v:.9f}" for u, v in uv]
    lines += [f"f {a+1}/{a+1} {b+1}/{b+1} {c+1}/{c+1}" for a, b, c in faces]
    path.write_text("\n".join(lines) + "\n")


def two_chart_sheet():
    """The wavy-sheet grid cut at x = 0 into two UV charts (seam vertices split): faces that
    touch x < 0 form chart 0 (u in [0, 0.45]), the rest chart 1 (u in [0.55, 1])."""
    faces, uv, rest = grid_mesh(24, 20)
    in_chart0 = (rest[faces][:, :, 0] < 0).any(axis=1)
    chart1_vertices = np.unique(faces[~in_chart0])
    copy = {v: len(rest) + i for i, v in enumerate(chart1_vertices)}
    faces = faces.copy()
    faces[~in_chart0] = np.vectorize(copy.get)(faces[~in_chart0])
    positions = np.concatenate([rest, rest[chart1_vertices]])
    uv = np.concatenate([uv * [0.45, 1.0], uv[chart1_vertices] * [0.45, 1.0] + [0.55, 0.0]]).astype(np.float32)
    keep = np.unique(faces)  # drop chart-1-only originals that no face uses any more
    remap = np.full(len(positions), -1)
    remap[keep] = np.arange(len(keep))
    face_chart = (~in_chart0).astype(int)
    return remap[faces].astype(np.int32), uv[keep], positions[keep], face_chart


def fake_model(path: Path, dataset) -> Path:
    """A model directory made by the library (random weights), small."""
    from safetensors.torch import save_file

    from mvtex.data.dataset import load_dataset
    from mvtex.tsnn.model import TSNN, PaperConfig
    from mvtex.tsnn.modeldir import MODEL_FORMAT, MODEL_VERSION, mesh_fingerprint

    ds = load_dataset(dataset)
    config = PaperConfig(pose_dim=ds.poses.shape[1], resolution=16, width=8, min_width=4)
    path.mkdir(parents=True)
    save_file(TSNN(config).state_dict(), str(path / "model.safetensors"))
    meta = {"format": MODEL_FORMAT, "version": MODEL_VERSION, "camera": "a", "architecture": config.to_dict(),
            "mesh": {"subdiv": 0, "num_base_vertices": ds.num_vertices, "num_vertices": ds.num_vertices,
                     "base_mesh": mesh_fingerprint(ds.faces, ds.uv)}}
    (path / "config.json").write_text(json.dumps(meta))
    return path


def brute_force_first_hit(origin, dirs, positions, faces, chunk=64):
    """Nearest hit (t > 0) of each ray against every triangle: Möller–Trumbore, float64.

    Returns tri (k,) (-1 = none), t (k,) in units of each direction, bary (k,3)."""
    p = positions[faces]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    s = origin - p[:, 0]
    q = np.cross(s, e1)
    tri = np.full(len(dirs), -1)
    best_t = np.full(len(dirs), np.inf)
    bary = np.zeros((len(dirs), 3))
    for start in range(0, len(dirs), chunk):
        d = dirs[start:start + chunk]
        h = np.cross(d[:, None, :], e2[None])
        a = np.einsum("mj,kmj->km", e1, h)
        with np.errstate(divide="ignore", invalid="ignore"):
            f = 1.0 / a
            u = f * np.einsum("mj,kmj->km", s, h)
            v = f * np.einsum("kj,mj->km", d, q)
            t = f * np.einsum("mj,mj->m", e2, q)[None]
        ok = (np.abs(a) > 0) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        t = np.where(ok, t, np.inf)
        i = np.argmin(t, axis=1)
        rows = np.arange(len(d))
        hit = np.isfinite(t[rows, i])
        tri[start:start + chunk] = np.where(hit, i, -1)
        best_t[start:start + chunk] = t[rows, i]
        bary[start:start + chunk] = np.stack([1 - u[rows, i] - v[rows, i], u[rows, i], v[rows, i]], 1)
    return tri, best_t, bary


def folded_sheet(nx=30, ny=30):
    """A sheet whose material slides into overhanging folds (gt) and a shifted, differently
    folded version (inferred). One UV chart, CCW seen from +z."""
    s, t = np.meshgrid(np.linspace(0, 1, nx), np.linspace(0, 1, ny))
    uv = np.stack([s.ravel(), t.ravel()], 1).astype(np.float32)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]).astype(np.int32)
    x = (uv[:, 0] - 0.5) * 0.6
    y = (uv[:, 1] - 0.5) * 0.8
    env = 0.6 + 0.4 * np.cos(2 * np.pi * y / 0.8)
    k = 2 * np.pi / 0.1
    gt = np.stack([0.8 * (x - 1.2 * 0.015 * env * np.sin(k * x)), y, 0.03 * env * np.cos(k * x)], 1)
    # Steep enough (slope > 2) to hide parts of itself from the oblique camera.
    inferred = np.stack([0.8 * x * 1.01 + 0.002, y, 0.04 * env * np.cos(k * x + 0.4)], 1)
    return faces, uv, gt.astype(np.float64), inferred.astype(np.float64)
def closest_points_on_triangles(p, a, b, c):
    """Closest points (k,3) on triangles (a, b, c) to points p (each (k,3)), by the region
    tests of Ericson's Real-Time Collision Detection (5.1.5), in NumPy."""
    ab, ac, ap, bp, cp = b - a, c - a, p - a, p - b, p - c
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = va + vb + vc
        out = a + (vb / denom)[:, None] * ab + (vc / denom)[:, None] * ac  # inside the face
        cases = [  # later cases win: from the edges to the corners, as the region tests nest
            ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + ((d4 - d3) / ((d4 - d3) + (d5 - d6)))[:, None] * (c - b)),
            ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + (d2 / (d2 - d6))[:, None] * ac),
            ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + (d1 / (d1 - d3))[:, None] * ab),
            ((d6 >= 0) & (d5 <= d6), c), ((d3 >= 0) & (d4 <= d3), b), ((d1 <= 0) & (d2 <= 0), a)]
    for mask, value in cases:
        out = np.where(mask[:, None], value, out)
    return out


def mesh_distance(points, vertices, faces, cutoff=0.05):
    """Distance (n,) of points to a triangle mesh: exact where the nearest vertex is closer
    than `cutoff` (every face that can hold the closest point is tested: its centroid lies
    within that vertex's distance plus the face's size), else a lower bound (the nearest
    vertex's distance less the largest face radius)."""
    from scipy.spatial import cKDTree

    points, vertices = np.asarray(points, np.float64), np.asarray(vertices, np.float64)
    corners = vertices[faces]
    centroids = corners.mean(axis=1)
    radius = np.linalg.norm(corners - centroids[:, None], axis=2).max()
    nearest, _ = cKDTree(vertices).query(points)
    out = nearest - radius
    near = np.flatnonzero(nearest < cutoff)
    lists = cKDTree(centroids).query_ball_point(points[near], nearest[near] + radius)
    owner = np.repeat(near, [len(faces_near) for faces_near in lists])
    face = np.concatenate([np.asarray(faces_near, np.int64) for faces_near in lists])
    q = closest_points_on_triangles(points[owner], *(corners[face, k] for k in range(3)))
    d = np.linalg.norm(points[owner] - q, axis=1)
    exact = np.full(len(points), np.inf)
    np.minimum.at(exact, owner, d)
    out[near] = exact[near]
    return out


# Tasks for process pools: spawned workers import them by module name, and `helpers` is on
# every process's path (pytest's `pythonpath`), where a test module's own name may not be.
def square(x: int) -> int:
    return x * x


def bad_input(x: int) -> int:
    from mvtex import InputError

    raise InputError(f"file{x}.npy", f"problem {x}")


@contextmanager
def held_elsewhere(claim):
    """Hold `claim` (a context manager, e.g. `claim_output(...)`) on another thread while the
    body runs: claims nest only within one thread's run, so this is how a second run on the
    same output is made in one process."""
    held, done = threading.Event(), threading.Event()

    def hold():
        with claim:
            held.set()
            done.wait(60)

    holder = threading.Thread(target=hold)
    holder.start()
    try:
        held.wait(60)
        yield
    finally:
        done.set()
        holder.join()


def three_camera_rig(width: int = 160, height: int = 120):
    """Three cameras 1.2 m in front of the origin, 12 degrees apart (a `Rig`)."""
    from mvtex.data.camera import look_at
    from mvtex.data.rig import Rig

    cams = []
    for name, angle in (("a", -12.0), ("b", 0.0), ("c", 12.0)):
        r = np.radians(angle)
        cams.append(look_at(name, (1.2 * np.sin(r), 0.05, 1.2 * np.cos(r)), (0, 0, 0), width=width, height=height,
                            focal=230.0))
    return Rig(tuple(cams))


def sheet_in_front():
    """Flat gt (z = 0), the inferred sheet 1 cm in front of it, and each camera's exact T_N
    (closed form: the ray through an inferred vertex meets the plane z = 0)."""
    size = 0.9
    faces, uv, rest = grid_mesh(36, 30, size=size)
    inferred = rest + np.array([0.0, 0.0, 0.01])
    rig = three_camera_rig()
    exact = {}
    for cam in rig:
        C = cam.center
        s = C[2] / (C[2] - inferred[:, 2])
        hit = C + s[:, None] * (inferred - C)
        exact[cam.name] = (hit[:, :2] + size / 2) / size
    return faces, uv, rest, inferred, rig, exact
