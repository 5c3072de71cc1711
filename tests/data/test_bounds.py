"""Numbers a record holds are checked against their bounds where it is read, so nothing
overflows later: a camera 1e200 m away, a vertex beyond float32 or beyond any rig.
Each is one line naming the file, and no numpy warning reaches stderr on the way (the
tests turn warnings into errors)."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest
from helpers import grid_mesh, one_line_error, run, write_obj

import mvtex


@pytest.fixture(autouse=True)
def warnings_are_errors():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield


@pytest.mark.parametrize("key, value", [("t", 1e200), ("t", 2e6), ("K", 1e39), ("dist", 1e300)])
def test_a_rig_beyond_its_bounds_is_refused_naming_the_file(key, value, tmp_path, front_rig, capsys):
    path = tmp_path / "rig.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("format", "mvtex-rig")
    fs.write("version", 1)
    fs.startWriteStruct("cameras", cv2.FileNode_SEQ)
    for cam in front_rig:
        arrays = {"K": cam.K.copy(), "dist": cam.dist.reshape(1, 5).copy(), "R": cam.R, "t": cam.t.reshape(3, 1).copy()}
        if cam.name == "b":
            arrays[key].flat[0 if key != "K" else 2] = value
        fs.startWriteStruct("", cv2.FileNode_MAP)
        fs.write("name", cam.name)
        fs.write("width", cam.width)
        fs.write("height", cam.height)
        for name in ("K", "dist", "R", "t"):
            fs.write(name, arrays[name])
        fs.endWriteStruct()
    fs.endWriteStruct()
    fs.release()
    for argv in (["rig", path], ["rig", path, "--to-colmap", tmp_path / "model"], ["rig", path, "--plot",
                                                                                   tmp_path / "rig.png"]):
        code, _, err = run(capsys, *argv)
        one_line_error(code, err, path, "camera 'b'", key)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.yaml"]


def test_an_imported_vertex_beyond_float32_is_one_line(tmp_path, capsys):
    faces, uv, rest = grid_mesh(4, 4)
    for k in range(2):
        write_obj(tmp_path / f"g{k}.obj", rest, uv, faces)
        write_obj(tmp_path / f"i{k}.obj", rest, uv, faces)
    far = rest.copy()
    far[3, 0] = 1e39
    write_obj(tmp_path / "i1.obj", far, uv, faces)
    code, _, err = run(capsys, "import", "--gt", tmp_path / "g*.obj", "--inferred", tmp_path / "i*.obj", "--out",
                       tmp_path / "ds", "--quiet")
    one_line_error(code, err, tmp_path / "i1.obj")
    assert not (tmp_path / "ds").exists()


def test_save_dataset_refuses_positions_beyond_the_bound(tmp_path, sheet):
    faces, uv, rest = sheet
    gt = np.stack([rest, rest]).astype(np.float64)
    for value in (1e39, 3e38, 2e6):
        far = gt.copy()
        far[1, 5, 2] = value
        with pytest.raises(mvtex.OptionError, match="gt"):
            mvtex.save_dataset(tmp_path / "ds", faces=faces, uv=uv, gt=far, inferred=gt, poses=np.zeros((2, 1)))
    assert list(tmp_path.iterdir()) == []

