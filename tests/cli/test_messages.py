"""Messages say what is wrong, in one line, naming what it concerns: a path holding a
newline stays on one line, a body file is named, numpy integers count as integers, and a
bad pose list or repeat count is a typed error naming the argument."""

from __future__ import annotations

import numpy as np
import pytest
from helpers import grid_mesh, one_line_error, run, write_obj

import mvtex

BODY_PLY = ("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
            "element face 2\nproperty list uchar int vertex_indices\nend_header\n"
            "0 0 -1\n1 0 -1\n0 1 -1\n1 1 -1\n3 0 1 2\n3 1 3 9\n")  # a face names vertex 9 of 4


def test_a_path_with_a_newline_is_one_line(tmp_path, capsys):
    odd = tmp_path / "two\nlines"
    for argv in (["render", odd, "--rig", "stereo", "--pose", 0, "--out", tmp_path / "out"],
                 ["synth", "--out", tmp_path / "f\x1bx", "--num-poses", 1],
                 ["rig", odd / "rig.yaml"]):
        code, _, err = run(capsys, *argv)
        assert code == 2 and len(err.strip().splitlines()) == 1 and "\x1b" not in err, err
    code, _, err = run(capsys, "render", odd, "--rig", "stereo", "--pose", 0, "--out", tmp_path / "out")
    one_line_error(code, err, "two\\nlines")


def test_a_body_file_that_does_not_fit_is_named(tmp_path, capsys):
    faces, uv, rest = grid_mesh(4, 4)
    for k in range(2):
        write_obj(tmp_path / f"g{k}.obj", rest, uv, faces)
        write_obj(tmp_path / f"i{k}.obj", rest, uv, faces)
        (tmp_path / f"b{k}.ply").write_text(BODY_PLY)
    code, _, err = run(capsys, "import", "--gt", tmp_path / "g*.obj", "--inferred", tmp_path / "i*.obj", "--body",
                       tmp_path / "b*.ply", "--out", tmp_path / "ds", "--quiet")
    one_line_error(code, err, tmp_path / "b0.ply", "out of range")


@pytest.mark.gl
def test_numpy_integers_are_integers_and_bad_poses_are_typed_errors(tiny_dataset, rig_file, slid_sheet0, gl):
    ds, rig = mvtex.load_dataset(tiny_dataset), mvtex.load_rig(rig_file)
    result = mvtex.evaluate(ds, rig, slid_sheet0, poses=[np.int64(1)], workers=np.int64(1), progress=False, ctx=gl)
    assert result.num_images == 2
    for poses, needle in (([], "no pose"), ([99], "out of range"), ([-1], "out of range"), ([0, 0], "twice")):
        with pytest.raises(mvtex.InputError, match=needle) as err:
            mvtex.evaluate(ds, rig, slid_sheet0, poses=poses, progress=False, ctx=gl)
        assert str(tiny_dataset) in str(err.value)


def test_run_bench_names_the_argument_it_refuses(tiny_dataset):
    with pytest.raises(mvtex.OptionError, match="^repeats must be"):
        mvtex.run_bench(tiny_dataset, "stereo", repeats=0, progress=False)
    with pytest.raises(mvtex.OptionError, match="^subdiv must be"):
        mvtex.run_bench(tiny_dataset, "stereo", subdiv=7, progress=False)
