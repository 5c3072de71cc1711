"""The writer policy through `mvtex.cli.main(argv)` and the `mvtex` process: reruns and
--overwrite keep a user's files, no output in or around an input, lookalike temporaries
survive, a full disk or a file-size limit is one line naming the output, a closed pipe is a
quiet exit, a killed render leaves no half folder, a demo resumes only its own options. The
same kinds through the public API are in tests/util/test_writer_policy.py."""

from __future__ import annotations

import errno
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers import one_line_error, run

from mvtex.util.output import MARKER

MVTEX = [sys.executable, "-m", "mvtex"]


def tree(path: Path) -> dict[str, bytes]:
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


@pytest.mark.slow
def test_a_rerun_and_overwrite_keep_a_file_the_user_put_into_the_output(tmp_path, capsys):
    out = tmp_path / "ds"
    code, _, err = run(capsys, "synth", "--out", out, "--num-poses", 10, "--quiet")
    assert code == 0, err
    (out / "notes.txt").write_text("my notes")
    before = tree(out)
    for extra in ([], ["--overwrite"]):
        code, _, err = run(capsys, "synth", "--out", out, "--num-poses", 10, "--seed", 1, "--quiet", *extra)
        one_line_error(code, err, out, "notes.txt")
        assert tree(out) == before


@pytest.mark.parametrize("case", ["slide-onto-dataset", "slide-into-dataset", "slide-around-dataset",
                                  "train-onto-texcoords", "predict-onto-model", "eval-heatmaps-into-texcoords"])
def test_an_output_in_or_around_an_input_is_refused(case, tmp_path, tiny_dataset, rig_file, slid_sheet0, capsys):
    data, tc = tmp_path / "work" / "data", tmp_path / "work" / "tc"
    shutil.copytree(tiny_dataset, data)
    shutil.copytree(slid_sheet0, tc)
    if case == "predict-onto-model":
        pytest.importorskip("torch")
        from helpers import fake_model

        fake_model(tmp_path / "work" / "model", tiny_dataset)
    before = tree(tmp_path / "work")
    argv, needle = {
        "slide-onto-dataset": (["slide", data, "--rig", rig_file, "--out", data], "is also an input"),
        "slide-into-dataset": (["slide", data, "--rig", rig_file, "--out", data / "ts"], "lies inside the input"),
        "slide-around-dataset": (["slide", data, "--rig", rig_file, "--out", tmp_path / "work"], "contains the input"),
        "train-onto-texcoords": (["train", data, "--texcoords", tc, "--cameras", "a", "--out", tc], "is also an input"),
        "predict-onto-model": (["predict", data, "--model", tmp_path / "work" / "model", "--out",
                                tmp_path / "work" / "model"], "is also an input"),
        "eval-heatmaps-into-texcoords": (["eval", data, "--rig", rig_file, "--texcoords", tc, "--heatmaps",
                                          tc / "heat"], "lies inside the input"),
    }[case]
    code, _, err = run(capsys, *argv, "--overwrite", "--quiet")
    one_line_error(code, err, needle)
    assert tree(tmp_path / "work") == before
    assert sorted(p.name for p in (tmp_path / "work").iterdir()) == sorted(
        ["data", "tc"] + (["model"] if case == "predict-onto-model" else []))


@pytest.mark.slow
def test_hidden_lookalike_temporaries_beside_out_survive(tmp_path, capsys):
    lookalikes = [tmp_path / ".ds.backup.tmp", tmp_path / ".ds.2024.aside", tmp_path / ".ds.lock"]
    for folder in lookalikes[:2]:
        folder.mkdir()
        (folder / "keep.txt").write_text("keep")
    lookalikes[2].write_text("mine")
    for _ in range(2):
        code, _, err = run(capsys, "synth", "--out", tmp_path / "ds", "--num-poses", 10, "--quiet")
        assert code == 0, err
    assert (lookalikes[0] / "keep.txt").read_text() == "keep" and (lookalikes[1] / "keep.txt").read_text() == "keep"
    assert lookalikes[2].read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["ds"] + [p.name for p in lookalikes])


def test_out_dot_with_overwrite_is_one_line(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    code, _, err = run(capsys, "synth", "--out", ".", "--num-poses", 10, "--overwrite", "--quiet")
    one_line_error(code, err, "current directory")
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_without_a_file_name_is_one_line_naming_the_output(tmp_path, capsys, monkeypatch):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", full)
    out = tmp_path / "ds"
    code, _, err = run(capsys, "synth", "--out", out, "--num-poses", 10, "--quiet")
    one_line_error(code, err, out, "No space left on device")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_file_size_limit_is_one_line_and_leaves_nothing(tmp_path):
    # A real limit (RLIMIT_FSIZE, as `ulimit -f`): writes past it fail with EFBIG, which
    # carries no file name; Python ignores SIGXFSZ, so the write fails instead of the process.
    script = ("import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000)); "
              "from mvtex.cli import main; sys.exit(main(sys.argv[1:]))")
    out = tmp_path / "ds"
    proc = subprocess.run([sys.executable, "-c", script, "synth", "--out", str(out), "--num-poses", "40", "--quiet"],
                          capture_output=True, text=True, timeout=300)
    one_line_error(proc.returncode, proc.stderr, out, "File too large")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_closed_pipe_is_a_quiet_exit(tmp_path):
    proc = subprocess.Popen([*MVTEX, "rig", "trapezoid12", "--json"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()  # `mvtex rig trapezoid12 --json | true`
    err = proc.stderr.read().decode()
    code = proc.wait(timeout=120)
    assert err == "" and code == 141, (code, err)


def test_a_closed_pipe_in_process_returns_141(capsys, monkeypatch):
    from mvtex.cli import main

    class Closed:
        def write(self, text):
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")

        def flush(self):
            raise BrokenPipeError(errno.EPIPE, "Broken pipe")

    monkeypatch.setattr(sys, "stdout", Closed())
    assert main(["rig", "stereo", "--json"]) == 141


@pytest.mark.slow
def test_a_killed_render_leaves_no_half_folder(tmp_path, tiny_dataset, rig_file):
    out = tmp_path / "render"
    # Killed (SIGKILL) after the first picture is written: the folder must not appear.
    script = ("import os, sys, signal; import mvtex.render.pose as r; real = r.save_png\n"
              "def save(path, image):\n    real(path, image); os.kill(os.getpid(), signal.SIGKILL)\n"
              "r.save_png = save\nfrom mvtex.cli import main; sys.exit(main(sys.argv[1:]))")
    proc = subprocess.run([sys.executable, "-c", script, "render", str(tiny_dataset), "--rig", str(rig_file),
                           "--pose", "0", "--out", str(out), "--quiet"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == -9, proc.stderr
    assert not out.exists()
    # The rerun cleans the killed run's stamped temporary and writes the whole folder.
    proc = subprocess.run([*MVTEX, "render", str(tiny_dataset), "--rig", str(rig_file), "--pose", "0", "--out",
                           str(out), "--quiet"], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["render"]
    assert json.loads((out / MARKER).read_text())["command"] == "render"


def test_a_demo_with_other_options_is_refused_not_reported(tmp_path, capsys, monkeypatch):
    import mvtex.synth.generate

    out = tmp_path / "demo"
    out.mkdir()
    (out / "demo.json").write_text(json.dumps({"options": {"num_poses": 10, "seed": 0, "tsnn": True}}))
    (out / MARKER).write_text(json.dumps({"command": "demo", "files": ["demo.json"]}))

    def no_work(*args, **kwargs):
        raise AssertionError("the demo started work instead of refusing")

    monkeypatch.setattr(mvtex.synth.generate, "write_synth", no_work)
    code, _, err = run(capsys, "demo", "--out", out, "--num-poses", 12, "--quiet")
    one_line_error(code, err, out, "other options", "num_poses=10")


def test_every_public_writer_goes_through_the_policy():
    """Each public function that takes an output path claims it (the `writer` decorator or
    an explicit claim), so none of them skips the checks the command line makes."""
    import inspect

    import mvtex

    writers = ["save_dataset", "save_texcoords", "save_rig", "write_synth", "import_sequences", "render_pose",
               "slide_dataset", "evaluate", "triangulate_pose", "train", "train_cameras", "predict", "novel_views",
               "stereo_preview", "write_board_png", "calibrate_folder", "run_demo"]
    for name in writers:
        function = getattr(mvtex, name)
        assert "overwrite" in inspect.signature(function).parameters, name
        source = inspect.getsource(inspect.unwrap(function)) if not hasattr(function, "__wrapped__") else ""
        assert hasattr(function, "__wrapped__") or "claim_" in source, name


# -- writers of other libraries: their failed writes are errors naming the output ------------------

def _limited(limit: int, *argv, cwd=None) -> subprocess.CompletedProcess:
    """`mvtex ARGV` under a file-size limit of `limit` bytes (RLIMIT_FSIZE, as `ulimit -f`):
    a write past it fails (EFBIG) inside whichever library writes."""
    script = (f"import resource, sys; resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit})); "
              "from mvtex.cli import main; sys.exit(main(sys.argv[1:]))")
    return subprocess.run([sys.executable, "-c", script, *map(str, argv)], capture_output=True, text=True,
                          timeout=300, cwd=cwd)


@pytest.mark.slow
def test_colmap_models_cut_short_by_a_full_disk_are_errors(tmp_path):
    out = tmp_path / "model"
    proc = _limited(300, "rig", "trapezoid12", "--to-colmap", out, "--quiet")
    one_line_error(proc.returncode, proc.stderr, out, "cannot write it")
    assert list(tmp_path.iterdir()) == []
    proc = _limited(300, "rig", "trapezoid12", "--to-colmap", out, "--text", "--quiet")
    one_line_error(proc.returncode, proc.stderr, out, "cannot write it")
    assert list(tmp_path.iterdir()) == []


def test_a_rig_file_cut_short_is_an_output_error_not_the_rigs(tmp_path):
    out = tmp_path / "pinhole.yaml"
    proc = _limited(400, "rig", "trapezoid12", "--undistort", "--out", out, "--quiet")
    line = one_line_error(proc.returncode, proc.stderr, out, "cannot write it", "File too large")
    assert "reader refuses" not in line
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_model_weights_cut_short_are_an_output_error(tmp_path, tiny_dataset, slid_sheet0):
    pytest.importorskip("torch")
    out = tmp_path / "model"
    proc = _limited(4000, "train", tiny_dataset, "--texcoords", slid_sheet0, "--cameras", "a", "--out", out,
                    "--quiet", cwd=tmp_path)
    one_line_error(proc.returncode, proc.stderr, out, "cannot write it", "File too large")
    assert list(tmp_path.iterdir()) == []
