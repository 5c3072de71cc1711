"""The fixtures every test folder shares: the one GL context, a small wavy cloth sheet, its
dataset, a two-camera rig file and texcoord sets slid from it."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import grid_mesh, wave

from mvtex.data.camera import look_at
from mvtex.data.rig import Rig, save_rig


@pytest.fixture(scope="session")
def gl():
    """The only place the GL context is created; checks GL errors around the session."""
    from mvtex.render.context import GLContext

    ctx = GLContext()
    assert ctx.error == "GL_NO_ERROR"
    yield ctx
    assert ctx.error == "GL_NO_ERROR"
    ctx.release()


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


@pytest.fixture(scope="session")
def rig_file(tmp_path_factory, front_rig):
    """The front rig as a rig YAML file (read only)."""
    path = tmp_path_factory.mktemp("rig") / "rig.yaml"
    save_rig(front_rig, path)
    return path


def _slid(tmp_path_factory, tiny_dataset, front_rig, poses, subdiv):
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions

    root = tmp_path_factory.mktemp("slid")
    save_rig(front_rig, root / "rig.yaml")
    slide_dataset(tiny_dataset, front_rig, root / "tc", poses=poses, options=SlideOptions(subdiv=subdiv), workers=1,
                  progress=False)
    return root / "tc"


@pytest.fixture(scope="session")
def slid_sheet(tmp_path_factory, tiny_dataset, front_rig, gl):
    """The tiny dataset slid from the front rig, poses 0, 2, 4, one subdivision (its rig is
    ../rig.yaml beside it; read only)."""
    return _slid(tmp_path_factory, tiny_dataset, front_rig, [0, 2, 4], 1)


@pytest.fixture(scope="session")
def slid_sheet0(tmp_path_factory, tiny_dataset, front_rig, gl):
    """The tiny dataset slid from the front rig, poses 0, 1, 2, no subdivision (read only)."""
    return _slid(tmp_path_factory, tiny_dataset, front_rig, [0, 1, 2], 0)


@pytest.fixture(scope="session")
def sheet_set(tiny_dataset, slid_sheet):
    """(dataset, rig file, texcoord set) of `slid_sheet`."""
    return tiny_dataset, slid_sheet.parent / "rig.yaml", slid_sheet
