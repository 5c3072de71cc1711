"""The writer policy in a shared folder, through `mvtex.cli.main(argv)`: what someone else
plants beside or inside an output (a link at the lock's or the manifest's name, a file
named like mvtex's transients, a bind mount of an input) is never written through, never
truncated, never deleted, and the run stops with exit 2 and one line."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from helpers import one_line_error, run

from mvtex.util.output import MARKER


def tree(path: Path) -> dict[str, bytes]:
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def synth(capsys, out: Path, *extra) -> tuple[int, str]:
    code, _, err = run(capsys, "synth", "--out", out, "--num-poses", 10, "--quiet", *extra)
    return code, err


@contextlib.contextmanager
def bind_mount(source: Path, target: Path):
    """`mount --bind source target` for the block; skips where the machine allows none."""
    target.mkdir()
    if not shutil.which("mount"):
        pytest.skip("no mount command")
    proc = subprocess.run(["mount", "--bind", str(source), str(target)], capture_output=True, text=True)
    if proc.returncode != 0:
        target.rmdir()
        pytest.skip(f"bind mounts are not allowed here ({proc.stderr.strip()})")
    try:
        yield target
    finally:
        subprocess.run(["umount", str(target)], check=True)
        target.rmdir()


# -- the lock -------------------------------------------------------------------------------------

@pytest.mark.parametrize("extra", [[], ["--overwrite"]])
def test_a_link_at_the_lock_name_is_never_written_through(tmp_path, capsys, extra):
    victim = tmp_path / "victim.txt"
    victim.write_text("precious\n")
    (tmp_path / ".ds.mvtex-lock").symlink_to(victim)
    code, err = synth(capsys, tmp_path / "ds", *extra)
    one_line_error(code, err, tmp_path / "ds", ".ds.mvtex-lock", "not mvtex's lock")
    assert victim.read_text() == "precious\n"
    assert (tmp_path / ".ds.mvtex-lock").is_symlink() and not (tmp_path / "ds").exists()


def test_a_hard_link_at_the_lock_name_is_refused(tmp_path, capsys):
    victim = tmp_path / "victim.txt"
    victim.write_text("12\n")  # looks like a lock's content, but it is someone's file
    os.link(victim, tmp_path / ".ds.mvtex-lock")
    code, err = synth(capsys, tmp_path / "ds")
    one_line_error(code, err, "not mvtex's lock")
    assert victim.read_text() == "12\n" and (tmp_path / ".ds.mvtex-lock").exists()


def test_a_users_file_named_like_the_lock_is_kept(tmp_path, capsys):
    mine = tmp_path / ".ds.mvtex-lock"
    mine.write_text("my notes about ds\n")
    for extra in ([], ["--overwrite"]):
        code, err = synth(capsys, tmp_path / "ds", *extra)
        one_line_error(code, err, ".ds.mvtex-lock", "not mvtex's lock")
        assert mine.read_text() == "my notes about ds\n"


def test_a_lock_left_by_a_killed_run_is_taken_over(tmp_path, capsys):
    (tmp_path / ".ds.mvtex-lock").write_text("999999\n")  # what a killed 0.3 run leaves: its pid
    code, err = synth(capsys, tmp_path / "ds")
    assert code == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ds"]


# -- the manifest and mvtex's transients ------------------------------------------------------------

def test_a_link_to_another_outputs_manifest_makes_no_folder_mvtexs(tmp_path, capsys):
    code, err = synth(capsys, tmp_path / "ds")
    assert code == 0, err
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "dataset.json").write_text("my notes")  # a name that manifest lists
    (mine / MARKER).symlink_to(tmp_path / "ds" / MARKER)
    before = tree(tmp_path)
    for extra in ([], ["--overwrite"]):
        code, err = synth(capsys, mine, *extra)
        one_line_error(code, err, mine, "did not write", "dataset.json")
    assert tree(tmp_path) == before and (mine / MARKER).is_symlink()


@pytest.mark.parametrize("name", [".notes.mvtex-lock", ".ds.mvtex-lock", ".x.mvtex-output.json.tmp",
                                  ".mvtex-output.json.tmp"])
@pytest.mark.slow
def test_a_hidden_file_named_like_a_transient_inside_an_output_is_the_users(name, tmp_path, capsys):
    out = tmp_path / "ds"
    code, err = synth(capsys, out)
    assert code == 0, err
    planted = out / name
    planted.write_text("the user's data\n")
    before = tree(out)
    for extra in ([], ["--overwrite"]):
        code, err = synth(capsys, out, "--seed", 1, *extra)
        one_line_error(code, err, out, "did not write")
    assert tree(out) == before


@pytest.mark.slow
def test_a_stamp_that_is_a_link_makes_no_temporary_mvtexs(tmp_path, capsys):
    code, err = synth(capsys, tmp_path / "ds")
    assert code == 0, err
    stamp = tmp_path / "real-stamp"
    stamp.write_text(json.dumps({"temporary_for": "ds"}))
    lookalike = tmp_path / ".ds.mvtex-abcdefgh.tmp"  # mvtex's temporary name, someone else's folder
    lookalike.mkdir()
    (lookalike / "keep.txt").write_text("keep")
    (lookalike / ".mvtex-temporary").symlink_to(stamp)
    code, err = synth(capsys, tmp_path / "ds")
    assert code == 0, err
    assert (lookalike / "keep.txt").read_text() == "keep"


# -- inputs --------------------------------------------------------------------------------------

def test_a_bind_mount_of_the_input_is_the_input(tmp_path, tiny_dataset, rig_file, slid_sheet0, capsys):
    work = tmp_path / "work"
    data, tc = work / "data", work / "tc"
    shutil.copytree(tiny_dataset, data)
    shutil.copytree(slid_sheet0, tc)
    before = tree(work)
    with bind_mount(data, tmp_path / "bound_data") as bound:
        code, _, err = run(capsys, "slide", data, "--rig", rig_file, "--out", bound, "--overwrite", "--quiet")
        one_line_error(code, err, bound, "is also an input")
        code, _, err = run(capsys, "slide", data, "--rig", rig_file, "--out", bound / "ts", "--overwrite", "--quiet")
        one_line_error(code, err, "lies inside the input")
    with bind_mount(tc, tmp_path / "bound_tc") as bound:
        pytest.importorskip("torch")
        code, _, err = run(capsys, "train", data, "--texcoords", tc, "--cameras", "a", "--out", bound, "--overwrite",
                           "--quiet")
        one_line_error(code, err, bound, "is also an input")
    assert tree(work) == before


def test_plots_and_rigs_are_never_written_onto_or_into_an_input(tmp_path, tiny_dataset, slid_sheet0, capsys):
    work = tmp_path / "work"
    data, tc = work / "data", work / "tc"
    shutil.copytree(tiny_dataset, data)
    shutil.copytree(slid_sheet0, tc)  # it records its rig: tc/rig.yaml is what views reads
    images = work / "images"
    (images / "cam0").mkdir(parents=True)
    (images / "cam0" / "0.png").write_bytes(b"\x89PNG a picture")
    code, _, err = run(capsys, "rig", "stereo", "--to-colmap", work / "model", "--quiet")
    assert code == 0, err
    before = tree(work)
    views = ["views", data, "--texcoords", tc, "--between", "a,b", "--steps", 2, "--out", tmp_path / "v"]
    for argv in ([*views, "--plot", tc / "rig.yaml"], [*views, "--plot", tc / "texcoords.json"],
                 [*views, "--plot", data / "gt.npy"], [*views, "--plot", tc / "new.png"],
                 ["calibrate", images, "--board", "charuco:5x4:0.04:0.03:DICT_4X4_50", "--out", images / "cam0" / "0.png"],
                 ["calibrate", images, "--board", "charuco:5x4:0.04:0.03:DICT_4X4_50", "--out", images / "rig.yaml"],
                 ["rig", "--from-colmap", work / "model", "--out", work / "model" / "cameras.bin"]):
        code, _, err = run(capsys, *argv, "--overwrite", "--quiet")
        one_line_error(code, err, argv[-1], "inside the input")
    assert tree(work) == before
    assert not (tmp_path / "v").exists()


# -- a killed run ---------------------------------------------------------------------------------

def test_a_folder_made_by_a_killed_run_inside_its_output_is_its_own(tmp_path):
    """A run writing a folder in place (demo) is killed right after a nested writer made a
    folder for its output: every later run, --overwrite or not, resumes or restarts it."""
    out = tmp_path / "demo"
    script = (
        "import os, signal, sys\n"
        "from pathlib import Path\n"
        "real = os.mkdir\n"
        "def mkdir(path, *args, **kwargs):\n"
        "    real(path, *args, **kwargs)\n"
        "    if os.path.basename(os.fspath(path)) == 'heatmaps': os.kill(os.getpid(), signal.SIGKILL)\n"
        "os.mkdir = mkdir\n"
        "from mvtex.util.output import claim_output\n"
        "out = Path(sys.argv[1])\n"
        "with claim_output(out, 'demo', in_place=True):\n"
        "    with claim_output(out / 'heatmaps' / 'stereo', 'eval'):\n"
        "        pass\n")
    proc = subprocess.run([sys.executable, "-c", script, str(out)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == -9, proc.stderr
    assert (out / "heatmaps").is_dir() and not any((out / "heatmaps").iterdir())
    from mvtex.util.output import claim_output, clear_output, foreign_entries

    assert foreign_entries(out) == []
    for overwrite in (False, True):
        with claim_output(out, "demo", in_place=True, overwrite=overwrite):
            clear_output(out, "demo")
    assert os.listdir(out) == [MARKER]


@pytest.mark.slow
def test_overwrite_given_to_a_command_reaches_the_writers_it_calls(tmp_path, tiny_dataset, slid_sheet0, capsys):
    """`train --cameras a,b --out OUT --overwrite` on another command's output: the model of
    camera a replaces OUT/a (another command's folder), as --overwrite asked; it is never
    refused with "pass --overwrite"."""
    pytest.importorskip("torch")
    out = tmp_path / "out"
    shutil.copytree(slid_sheet0, out)  # a slide set: its camera folder a is slide's
    code, _, err = run(capsys, "train", tiny_dataset, "--texcoords", slid_sheet0, "--cameras", "a,b", "--out",
                       out, "--overwrite", "--quiet")
    assert code == 0, err
    assert (out / "a" / "model.safetensors").is_file() and (out / "b" / "model.safetensors").is_file()
    assert json.loads((out / MARKER).read_text())["command"] == "train"
