"""Shared fixtures: the one GL context, a small wavy cloth sheet, a dataset and a rig.

The sheet is made here from closed forms (no mvtex code involved) so tests can compare
mvtex against independent computations.
"""

from __future__ import annotations

import numpy as np
import pytest

from mvtex.data.camera import look_at
from mvtex.data.rig import Rig


@pytest.fixture(scope="session")
def gl():
    """The only place the GL context is created; checks GL errors around the session."""
    from mvtex.render.context import GLContext

    ctx = GLContext()
    assert ctx.error == "GL_NO_ERROR"
    yield ctx
    assert ctx.error == "GL_NO_ERROR"
    ctx.release()


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


@pytest.fixture(scope="session")
def sheet():
    faces, uv, rest = grid_mesh()
    return faces, uv, rest


@pytest.fixture(scope="session")
def front_rig() -> Rig:
    """Two 160x120 cameras 1.2 m in front of the sheet, 20 degrees apart."""
    cams = []
    for name, angle in (("a", -10.0), ("b", 10.0)):
        r = np.radians(angle)
        cams.append(look_at(name, (1.2 * np.sin(r), 0.05, 1.2 * np.cos(r)), (0, 0, 0), width=160, height=120, focal=260.0))
    return Rig(tuple(cams))


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory, sheet):
    """A 6-pose dataset of the wavy sheet: gt folds 1.5 cm deep, inferred a flattened version."""
    from mvtex.data.dataset import save_dataset

    faces, uv, rest = sheet
    phases = np.linspace(0, 2.5, 6)
    gt = np.stack([wave(rest, 0.015, p) for p in phases])
    inferred = np.stack([wave(rest, 0.004, p) for p in phases])
    poses = np.stack([np.sin(phases), np.cos(phases)], axis=1)
    path = tmp_path_factory.mktemp("data") / "sheet"
    save_dataset(path, faces=faces, uv=uv, gt=gt, inferred=inferred, poses=poses, name="sheet", rest=rest)
    return path


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
