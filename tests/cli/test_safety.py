"""What mvtex guarantees about a user's files, probe by probe: outputs never delete what mvtex
did not write, one run per output, resumable and content-keyed slides, safe camera names,
sizes and numbers checked before use, one-line errors instead of tracebacks."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from helpers import bad_input, fake_model, held_elsewhere, one_line_error, run, square

from mvtex.cli import main
from mvtex.data.camera import Camera
from mvtex.data.rig import Rig, save_rig
from mvtex.util.errors import InputError, OutputError
from mvtex.util.output import MARKER, _temporary, _write_marker, claim_output, replace_path

MVTEX = [sys.executable, "-m", "mvtex"]


def tree(path: Path) -> dict[str, bytes]:
    return {str(p.relative_to(path)): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def copy_set(slid_sheet0, tmp_path) -> Path:
    tc = tmp_path / "tc"
    shutil.copytree(slid_sheet0, tc)
    return tc


# -- outputs ---------------------------------------------------------------------------

def foreign(tmp_path) -> Path:
    folder = tmp_path / "o"
    folder.mkdir()
    (folder / "keep.txt").write_text("x")
    return folder


@pytest.mark.parametrize("command", ["synth", "import", "render", "slide", "triangulate", "train", "predict",
                                     "demo"])
def test_every_writer_refuses_a_folder_it_did_not_write(command, tmp_path, tiny_dataset, rig_file, slid_sheet0, capsys):
    out = foreign(tmp_path)
    argv = {
        "synth": ["synth", "--out", out, "--num-poses", 10],
        "import": ["import", "--out", out, "--gt", tmp_path / "*.obj", "--inferred", tmp_path / "*.obj"],
        "render": ["render", tiny_dataset, "--rig", rig_file, "--pose", 0, "--out", out],
        "slide": ["slide", tiny_dataset, "--rig", rig_file, "--out", out],
        "triangulate": ["triangulate", tiny_dataset, "--rig", rig_file, "--texcoords", slid_sheet0, "--pose", 0, "--out", out],
        "train": ["train", tiny_dataset, "--texcoords", slid_sheet0, "--cameras", "a", "--out", out],
        "predict": ["predict", tiny_dataset, "--model", tmp_path / "m", "--out", out],
        "demo": ["demo", "--out", out],
    }[command]
    if command == "import":
        from helpers import grid_mesh, write_obj

        faces, uv, rest = grid_mesh(4, 4)
        write_obj(tmp_path / "g.obj", rest, uv, faces)
    if command == "predict":
        pytest.importorskip("torch")
        fake_model(tmp_path / "m", tiny_dataset)
    code, _, err = run(capsys, *argv, "--quiet" if command not in ("synth",) else "--json")
    one_line_error(code, err, out, "--overwrite")
    assert tree(out) == {"keep.txt": b"x"}


@pytest.mark.slow
def test_own_output_is_replaced_and_overwrite_never_deletes_a_users_file(tmp_path, capsys):
    out = foreign(tmp_path)
    code, _, err = run(capsys, "synth", "--out", out, "--num-poses", 10, "--overwrite", "--json")
    one_line_error(code, err, out, "keep.txt")
    assert tree(out) == {"keep.txt": b"x"}
    (out / "keep.txt").unlink()  # an empty folder is free
    code, _, err = run(capsys, "synth", "--out", out, "--num-poses", 10, "--json")
    assert code == 0, err
    assert json.loads((out / MARKER).read_text())["command"] == "synth"
    first = (out / "gt.npy").read_bytes()
    code, _, err = run(capsys, "synth", "--out", out, "--num-poses", 11, "--seed", 1, "--json")  # its own output: no flag needed
    assert code == 0, err
    assert (out / "gt.npy").read_bytes() != first
    code, _, err = run(capsys, "import", "--out", out, "--gt", "x*.obj", "--inferred", "y*.obj")  # another command's
    one_line_error(code, err, "the output of `mvtex synth`")
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries, no lock left


def test_a_file_at_out_and_an_uncreatable_out_exit_2(tmp_path, capsys):
    (tmp_path / "f").write_text("mine")
    code, _, err = run(capsys, "synth", "--out", tmp_path / "f", "--num-poses", 10)
    one_line_error(code, err, tmp_path / "f", "not a directory")
    assert (tmp_path / "f").read_text() == "mine"
    code, _, err = run(capsys, "synth", "--out", tmp_path / "f" / "sub", "--num-poses", 10)
    one_line_error(code, err, tmp_path / "f" / "sub")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_an_unwritable_parent_exits_2(tmp_path, capsys):
    locked = tmp_path / "ro"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        code, _, err = run(capsys, "synth", "--out", locked / "d", "--num-poses", 10)
        one_line_error(code, err, locked / "d")
    finally:
        locked.chmod(0o700)


def test_a_second_run_on_the_same_output_is_refused_with_the_holders_pid(tmp_path, tiny_dataset, rig_file, capsys):
    out = tmp_path / "tc"
    with held_elsewhere(claim_output(out, "slide")):
        code, _, err = run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--out", out, "--quiet")
    one_line_error(code, err, out, f"in use by pid {os.getpid()}")
    assert not list(tmp_path.glob(".tc.*lock"))


def test_replacing_renames_aside_before_deleting(tmp_path, monkeypatch):
    target, new = tmp_path / "out", tmp_path / "new"
    target.mkdir()
    (target / "old.txt").write_text("old")
    _write_marker(target, "slide")  # mvtex wrote all of it: it may be replaced
    new.mkdir()
    (new / "new.txt").write_text("new")
    seen = []
    real_replace = os.replace

    def replace(src, dst):
        # When the new version is renamed in, the old one must still exist somewhere.
        if Path(src) == new:
            asides = [p for p in tmp_path.glob(".out.*.aside/out/old.txt")]
            seen.append([p.read_text() for p in asides])
            raise OSError(28, "No space left on device", str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(OSError):
        replace_path(new, target)
    assert seen == [["old"]]
    assert (target / "old.txt").read_text() == "old" and (new / "new.txt").exists()
    assert not list(tmp_path.glob(".out.*"))


# -- slide: resume keys, done masks, finishing ---------------------------------------------

def _slide(ds, rig, out, **kw):
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions

    return slide_dataset(ds, rig, out, poses=[0, 1, 2, 3], options=SlideOptions(subdiv=0), workers=1,
                         progress=False, **kw)


def _interrupt_after(monkeypatch, calls: int):
    import mvtex.sliding.dataset as sliding

    real = sliding._slide_chunk
    count = {"n": 0}

    def chunk(*args):
        count["n"] += 1
        if count["n"] > calls:
            raise KeyboardInterrupt
        return real(*args)

    monkeypatch.setattr(sliding, "_CHUNK", 1)
    monkeypatch.setattr(sliding, "_slide_chunk", chunk)
    return count


def test_done_mask_is_saved_after_every_chunk(tmp_path, tiny_dataset, front_rig, monkeypatch, gl):
    _interrupt_after(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        _slide(tiny_dataset, front_rig, tmp_path / "tc")
    done = [np.load(tmp_path / "tc.partial" / c / "done.npy") for c in ("a", "b")]
    assert sum(int(d.sum()) for d in done) == 3


def test_resume_key_includes_the_content_of_the_arrays(tmp_path, tiny_dataset, front_rig, monkeypatch, gl, capsys):
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    count = _interrupt_after(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        _slide(ds, front_rig, tmp_path / "tc")
    # Replace gt in place (same shape, same path): the unfinished rows are from the old data.
    gt = np.load(ds / "gt.npy")
    np.save(ds / "gt.npy", gt[::-1].copy())
    count["n"] = -100
    _slide(ds, front_rig, tmp_path / "tc")
    assert "starting over" in capsys.readouterr().err
    monkeypatch.undo()
    _slide(ds, front_rig, tmp_path / "fresh")
    for cam in ("a", "b"):
        assert np.array_equal(np.load(tmp_path / "tc" / cam / "displacement.npy"),
                              np.load(tmp_path / "fresh" / cam / "displacement.npy"))


def test_a_failure_while_finishing_leaves_a_partial_the_rerun_completes(tmp_path, tiny_dataset, front_rig,
                                                                        monkeypatch, gl):
    import mvtex.data.partial_set
    import mvtex.sliding.dataset as sliding

    real = mvtex.data.partial_set.replace_path

    def fail(src, dst):  # only the last step: renaming the finished set in
        if Path(src).name == "tc.partial" and Path(dst).name == "tc":
            raise OSError(28, "No space left on device", str(dst))
        return real(src, dst)

    monkeypatch.setattr(mvtex.data.partial_set, "replace_path", fail)
    with pytest.raises(OutputError, match="tc: cannot write it"):
        _slide(tiny_dataset, front_rig, tmp_path / "tc")
    monkeypatch.undo()
    # The rerun has nothing left to compute: any chunk would fail.
    monkeypatch.setattr(sliding, "_slide_chunk", lambda *a: pytest.fail("recomputed a finished chunk"))
    _slide(tiny_dataset, front_rig, tmp_path / "tc")
    assert not (tmp_path / "tc.partial").exists()
    assert not list((tmp_path / "tc").rglob("done.npy"))


def test_a_partial_without_done_masks_is_redone_not_refused(tmp_path, tiny_dataset, front_rig, monkeypatch, gl):
    _interrupt_after(monkeypatch, 2)
    with pytest.raises(KeyboardInterrupt):
        _slide(tiny_dataset, front_rig, tmp_path / "tc")
    monkeypatch.undo()
    for cam in ("a", "b"):
        (tmp_path / "tc.partial" / cam / "done.npy").unlink()
    _slide(tiny_dataset, front_rig, tmp_path / "tc")
    _slide(tiny_dataset, front_rig, tmp_path / "fresh")
    assert tree(tmp_path / "tc") == tree(tmp_path / "fresh")


def test_a_kill_while_saving_a_done_mask_leaves_nothing_in_the_finished_set(tmp_path, tiny_dataset, front_rig,
                                                                             monkeypatch, gl):
    """A kill between the two renames of a done-mask save leaves the mask's hidden
    temporary and aside copies in the camera's folder (and no done.npy); the rerun redoes
    that camera and the finished set holds exactly what an uninterrupted run writes."""
    _interrupt_after(monkeypatch, 3)
    with pytest.raises(KeyboardInterrupt):
        _slide(tiny_dataset, front_rig, tmp_path / "tc")
    monkeypatch.undo()
    cam = tmp_path / "tc.partial" / "a"
    for kind in ("aside", "tmp"):  # named and stamped as mvtex's own
        shutil.copy(cam / "done.npy", _temporary(cam / "done.npy", kind) / "done.npy")
    (cam / "done.npy").unlink()
    _slide(tiny_dataset, front_rig, tmp_path / "tc")
    _slide(tiny_dataset, front_rig, tmp_path / "fresh")
    assert tree(tmp_path / "tc") == tree(tmp_path / "fresh")


def test_a_foreign_partial_folder_is_not_deleted(tmp_path, tiny_dataset, rig_file, capsys):
    mine = foreign(tmp_path)
    mine.rename(tmp_path / "tc.partial")
    code, _, err = run(capsys, "slide", tiny_dataset, "--rig", rig_file, "--out", tmp_path / "tc", "--quiet")
    one_line_error(code, err, "tc.partial")
    assert tree(tmp_path / "tc.partial") == {"keep.txt": b"x"}


# -- names -----------------------------------------------------------------------------

@pytest.mark.parametrize("name", ["../../x", "/abs/x", "a/b", ".", "..", "mesh.npz", "Rig.YAML", ".hidden", "",
                                  "a" * 65, "x\ny", "ok."])
def test_hostile_camera_names_in_a_rig_are_refused(name, tmp_path, tiny_dataset, front_rig, capsys):
    rig = tmp_path / "rig.yaml"
    text = (tmp_path / "src.yaml")
    save_rig(front_rig, text)
    rig.write_text(text.read_text().replace("name: a", f"name: {json.dumps(name)}", 1))
    work = tmp_path / "work"
    work.mkdir()
    code, _, err = run(capsys, "slide", tiny_dataset, "--rig", rig, "--out", work / "tc", "--quiet")
    one_line_error(code, err, rig)
    assert list(work.iterdir()) == [] and sorted(p.name for p in tmp_path.iterdir()) == ["rig.yaml", "src.yaml",
                                                                                        "work"]


def test_camera_names_are_checked_in_texcoord_sets_and_models(tmp_path, slid_sheet0, tiny_dataset, rig_file, capsys):
    tc = copy_set(slid_sheet0, tmp_path)
    meta = json.loads((tc / "texcoords.json").read_text())
    meta["cameras"] = ["../../x"]
    (tc / "texcoords.json").write_text(json.dumps(meta))
    code, _, err = run(capsys, "eval", tiny_dataset, "--rig", rig_file, "--texcoords", tc, "--quiet")
    one_line_error(code, err, tc / "texcoords.json", "camera name")
    pytest.importorskip("torch")
    model = fake_model(tmp_path / "m", tiny_dataset)
    config = json.loads((model / "config.json").read_text())
    config["camera"] = "../escape"
    (model / "config.json").write_text(json.dumps(config))
    code, _, err = run(capsys, "predict", tiny_dataset, "--model", model, "--out", tmp_path / "p", "--quiet")
    one_line_error(code, err, model / "config.json", "camera name")
    assert not (tmp_path / "p").exists() and not (tmp_path / "escape").exists()


# -- sizes -------------------------------------------------------------------------------


def test_model_sizes_are_refused_before_anything_is_built(tmp_path, tiny_dataset, capsys):
    pytest.importorskip("torch")
    model = fake_model(tmp_path / "m", tiny_dataset)
    code, _, err = run(capsys, "predict", tiny_dataset, "--model", model, "--out", tmp_path / "p", "--quiet")
    assert code == 0, err
    config = json.loads((model / "config.json").read_text())
    for change, needle in ((("mesh", "subdiv", 12), "subdiv"), (("architecture", "resolution", 1 << 20), "large"),
                           (("architecture", "width", 1 << 30), "large")):
        bad = json.loads(json.dumps(config))
        bad[change[0]][change[1]] = change[2]
        (model / "config.json").write_text(json.dumps(bad))
        t0 = time.perf_counter()
        code, _, err = run(capsys, "predict", tiny_dataset, "--model", model, "--out", tmp_path / "p2", "--quiet")
        one_line_error(code, err, model / "config.json", needle)
        assert time.perf_counter() - t0 < 20
    # An architecture that the weights do not back: compared on the meta device, not allocated.
    bad = json.loads(json.dumps(config))
    bad["architecture"]["width"] = 1024
    (model / "config.json").write_text(json.dumps(bad))
    code, _, err = run(capsys, "predict", tiny_dataset, "--model", model, "--out", tmp_path / "p2", "--quiet")
    one_line_error(code, err, model / "model.safetensors", "the architecture in config.json needs")


@pytest.mark.parametrize("key,value,needle", [
    ("width", "abc", "'width' must be an integer"), ("width", "20000", "1..16384"), ("height", "0", "1..16384"),
    ("width", "100.5", "integer"),
])
def test_rig_image_sizes(key, value, needle, tmp_path, tiny_dataset, front_rig, capsys):
    src = tmp_path / "src.yaml"
    save_rig(front_rig, src)
    lines = src.read_text().splitlines()
    i = next(i for i, line in enumerate(lines) if line.strip().startswith(f"{key}:"))
    lines[i] = lines[i].split(":")[0] + f": {value}"
    rig = tmp_path / "rig.yaml"
    rig.write_text("\n".join(lines) + "\n")
    code, _, err = run(capsys, "slide", tiny_dataset, "--rig", rig, "--out", tmp_path / "tc", "--quiet")
    one_line_error(code, err, rig, needle)


def test_rig_intrinsics_and_distortion(tmp_path, tiny_dataset, front_rig, capsys):
    cam = front_rig["a"]
    K = cam.K.copy()
    K[0, 0] = 0
    with pytest.raises(ValueError, match="fx, fy > 0"):
        Camera("a", 160, 120, K=K, R=cam.R, t=cam.t)
    distorted = tmp_path / "d.yaml"
    save_rig(Rig((Camera("a", 160, 120, K=cam.K, R=cam.R, t=cam.t, dist=[0.1, 0, 0, 0, 0]),)), distorted)
    for argv in (["slide", tiny_dataset, "--out", tmp_path / "tc"], ["bench", tiny_dataset, "--poses", "0:1"]):
        code, _, err = run(capsys, *argv, "--rig", distorted, "--quiet")
        one_line_error(code, err, distorted, "distortion")
    away = tmp_path / "away.yaml"
    save_rig(Rig((Camera("a", 160, 120, K=cam.K, R=cam.R, t=cam.t + np.array([9.0, 0, 0])),)), away)
    code, _, err = run(capsys, "slide", tiny_dataset, "--rig", away, "--out", tmp_path / "tc", "--quiet")
    one_line_error(code, err, away, "sees nothing")
    assert not (tmp_path / "tc").exists()


# -- bad numbers -------------------------------------------------------------------------

def test_non_finite_and_huge_displacements_are_refused(tmp_path, slid_sheet0, tiny_dataset, rig_file, capsys):
    tc = copy_set(slid_sheet0, tmp_path)
    d = np.load(tc / "a" / "displacement.npy")
    for value, needle in ((np.nan, "NaN or infinite"), (np.inf, "NaN or infinite"), (1e30, "more than")):
        bad = d.copy()
        bad[1, 7, 0] = value
        np.save(tc / "a" / "displacement.npy", bad)
        code, out, err = run(capsys, "eval", tiny_dataset, "--rig", rig_file, "--texcoords", tc, "--json", "--quiet")
        one_line_error(code, err, tc / "a" / "displacement.npy", needle)
        assert out == ""


def test_pose_indices_of_a_texcoord_set_must_be_in_range(tmp_path, slid_sheet0, tiny_dataset, rig_file, capsys):
    tc = copy_set(slid_sheet0, tmp_path)
    meta = json.loads((tc / "texcoords.json").read_text())
    for poses, needle in (([-1, 1, 2], "pose index -1"), ([0, 1, 6], "pose index 6"), ([0, 0, 1], "twice"),
                          ([0, 1.5, 2], "integer")):
        (tc / "texcoords.json").write_text(json.dumps({**meta, "poses": poses}))
        code, _, err = run(capsys, "eval", tiny_dataset, "--rig", rig_file, "--texcoords", tc, "--quiet")
        one_line_error(code, err, tc / "texcoords.json", needle)
    (tc / "texcoords.json").write_text(json.dumps(meta).replace('"subdiv": 0', '"subdiv": NaN'))
    code, _, err = run(capsys, "eval", tiny_dataset, "--rig", rig_file, "--texcoords", tc, "--quiet")
    one_line_error(code, err, tc / "texcoords.json")


def test_nan_in_dataset_arrays_names_the_file(tmp_path, tiny_dataset, rig_file, capsys):
    for name in ("gt.npy", "inferred.npy", "poses.npy"):
        ds = tmp_path / name.split(".")[0]
        shutil.copytree(tiny_dataset, ds)
        a = np.load(ds / name)
        a.reshape(-1)[5] = np.inf
        np.save(ds / name, a)
        code, _, err = run(capsys, "slide", ds, "--rig", rig_file, "--out", tmp_path / "tc", "--quiet")
        one_line_error(code, err, ds / name, "NaN or infinite")


@pytest.mark.parametrize("argv,needle", [
    (["triangulate", "{ds}", "--rig", "{rig}", "--texcoords", "{tc}", "--pose", "0", "--max-reprojection-px", "-1"],
     "--max-reprojection-px"),
    (["triangulate", "{ds}", "--rig", "{rig}", "--texcoords", "{tc}", "--pose", "0", "--max-surface-distance", "nan"],
     "--max-surface-distance"),
    (["slide", "{ds}", "--rig", "{rig}", "--max-displacement", "0"], "--max-displacement"),
    (["slide", "{ds}", "--rig", "{rig}", "--max-displacement", "inf"], "--max-displacement"),
    (["slide", "{ds}", "--rig", "{rig}", "--workers", "0"], "--workers"),
    (["eval", "{ds}", "--rig", "{rig}", "--texcoords", "{tc}", "--workers", "-2"], "--workers"),
    (["train", "{ds}", "--texcoords", "{tc}", "--cameras", "a", "--epochs", "0"], "--epochs"),
    (["train", "{ds}", "--texcoords", "{tc}", "--cameras", "a", "--resolution", "0"], "--resolution"),
    (["train", "{ds}", "--texcoords", "{tc}", "--cameras", "a", "--resolution", "100"], "--resolution"),
    (["train", "{ds}", "--texcoords", "{tc}", "--cameras", "a", "--device", "banana"], "--device"),
    (["demo", "--num-poses", "3"], "--num-poses"),
    (["synth", "--out", "{out}", "--num-poses", "-5"], "--num-poses"),
])
def test_bad_option_values_exit_2_in_one_line(argv, needle, tmp_path, tiny_dataset, rig_file, slid_sheet0, capsys):
    values = {"{ds}": tiny_dataset, "{rig}": rig_file, "{tc}": slid_sheet0, "{out}": tmp_path / "o"}
    argv = [str(values.get(a, a)) for a in argv]
    if argv[0] in ("slide", "triangulate", "train", "demo"):
        argv += ["--out", str(tmp_path / "o")]
    code, out, err = run(capsys, *argv, "--quiet" if argv[0] != "synth" else "--json")
    one_line_error(code, err, needle)
    assert out == "" and not (tmp_path / "o").exists()


def test_empty_validation_split_exits_2(tmp_path, tiny_dataset, slid_sheet0, capsys):
    pytest.importorskip("torch")
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    (ds / "split.json").write_text(json.dumps({"train": [0, 1, 2], "val": [], "test": [3, 4, 5]}))
    code, _, err = run(capsys, "train", ds, "--texcoords", slid_sheet0, "--cameras", "a", "--out", tmp_path / "m",
                       "--epochs", "1", "--quiet")
    one_line_error(code, err, "validation poses")
    assert not (tmp_path / "m").exists()


def test_json_output_is_strict(tmp_path, slid_sheet0, tiny_dataset, rig_file, capsys):
    from mvtex.util.files import dumps_strict

    assert json.loads(dumps_strict({"a": float("nan"), "b": [np.float32(np.inf), 1.5]})) == {"a": None, "b": [None, 1.5]}
    code, out, err = run(capsys, "eval", tiny_dataset, "--rig", rig_file, "--texcoords", slid_sheet0, "--json", "--quiet")
    assert code == 0, err

    def reject(constant):
        raise ValueError(constant)

    result = json.loads(out, parse_constant=reject)
    assert result["num_images"] == 6


# -- truncated and corrupt files -----------------------------------------------------------

def test_truncated_npz_in_every_loader(tmp_path, tiny_dataset, rig_file, slid_sheet0, capsys):
    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    data = (ds / "mesh.npz").read_bytes()
    (ds / "mesh.npz").write_bytes(data[: len(data) // 2])
    for argv in (["render", ds, "--rig", rig_file, "--pose", 0, "--out", tmp_path / "o"],
                 ["slide", ds, "--rig", rig_file, "--out", tmp_path / "o"],
                 ["eval", ds, "--rig", rig_file, "--texcoords", slid_sheet0],
                 ["triangulate", ds, "--rig", rig_file, "--texcoords", slid_sheet0, "--pose", 0, "--out", tmp_path / "o"],
                 ["train", ds, "--texcoords", slid_sheet0, "--cameras", "a", "--out", tmp_path / "o"],
                 ["bench", ds, "--rig", rig_file]):
        code, _, err = run(capsys, *argv, "--quiet")
        one_line_error(code, err, ds / "mesh.npz", "not a readable .npz")
    tc = copy_set(slid_sheet0, tmp_path)
    (tc / "mesh.npz").write_bytes(b"PK\x03\x04" + b"\x00" * 40)
    code, _, err = run(capsys, "eval", tiny_dataset, "--rig", rig_file, "--texcoords", tc, "--quiet")
    one_line_error(code, err, tc / "mesh.npz")
    assert not (tmp_path / "o").exists()


# -- interruptions and parallel runs -------------------------------------------------------

def _wait_for_progress(partial: Path, proc, timeout: float = 120.0) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        try:
            if sum(int(np.load(partial / c / "done.npy").sum()) for c in ("a", "b")) >= 2:
                return
        except (OSError, ValueError, EOFError):
            pass
        assert proc.poll() is None, "finished before it could be interrupted"
        time.sleep(0.02)
    pytest.fail("no progress")


def _children(pid: int) -> list[int]:
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    return [int(p) for p in out.split()]


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    state = Path(f"/proc/{pid}/stat").read_text().split()[2] if Path(f"/proc/{pid}/stat").exists() else "X"
    return state not in ("Z", "X")


@pytest.fixture(scope="module")
def slow_dataset(tmp_path_factory, sheet):
    """40 poses of the sheet: enough jobs to interrupt a run in the middle."""
    return _wave_sheet(tmp_path_factory.mktemp("slow") / "sheet", sheet, 40)


def _wave_sheet(path: Path, sheet, num_poses: int) -> Path:
    """A dataset of the sheet waving through `num_poses` phases (gt 15 mm, inferred 4 mm waves)."""
    from helpers import wave

    from mvtex.data.dataset import save_dataset

    faces, uv, rest = sheet
    phases = np.linspace(0, 6, num_poses)
    save_dataset(path, faces=faces, uv=uv, gt=np.stack([wave(rest, 0.015, p) for p in phases]),
                 inferred=np.stack([wave(rest, 0.004, p) for p in phases]),
                 poses=phases[:, None], rest=rest)
    return path


def _one_process_set(base: Path, dataset: Path, front_rig) -> Path:
    """BASE/rig.yaml and BASE/tc, the dataset slid_sheet0 by one process at subdivision 0."""
    save_rig(front_rig, base / "rig.yaml")
    assert main(["slide", str(dataset), "--rig", str(base / "rig.yaml"), "--out", str(base / "tc"),
                 "--subdiv", "0", "--workers", "1", "--quiet"]) == 0
    return base


@pytest.fixture(scope="module")
def reference_set(tmp_path_factory, slow_dataset, front_rig, gl):
    return _one_process_set(tmp_path_factory.mktemp("ref"), slow_dataset, front_rig)


@pytest.fixture(scope="module")
def long_run(tmp_path_factory, sheet, front_rig, gl):
    """150 poses of the sheet and their one-process texcoord set: a two-worker run of it
    lasts long enough after its first chunks to be interrupted on a loaded machine."""
    base = tmp_path_factory.mktemp("long")
    return _one_process_set(base, _wave_sheet(base / "sheet", sheet, 150), front_rig)


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGINT])
def test_kill_and_resume_with_workers_is_bit_identical(sig, tmp_path, long_run):
    out = tmp_path / "tc"
    reference_set = long_run
    argv = MVTEX + ["slide", str(long_run / "sheet"), "--rig", str(long_run / "rig.yaml"), "--out", str(out),
                    "--subdiv", "0", "--workers", "2", "--quiet"]
    # A shell's background jobs start with SIGINT ignored, and Python then keeps ignoring it:
    # give the command the default disposition an interactive user's has.
    proc = subprocess.Popen(argv, stderr=subprocess.PIPE,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    _wait_for_progress(tmp_path / "tc.partial", proc)
    workers = _children(proc.pid)
    proc.send_signal(sig)
    proc.wait(timeout=60)
    assert proc.returncode == (-9 if sig == signal.SIGKILL else 130), proc.stderr.read()
    deadline = time.monotonic() + 10
    while any(_alive(w) for w in workers) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not [w for w in workers if _alive(w)], "orphaned workers"
    assert not out.exists()
    done = sum(int(np.load(tmp_path / "tc.partial" / c / "done.npy").sum()) for c in ("a", "b"))
    assert 2 <= done < 300
    rerun = subprocess.run(argv, capture_output=True, text=True)
    assert rerun.returncode == 0, rerun.stderr
    assert tree(out) == tree(reference_set / "tc") | {MARKER: (out / MARKER).read_bytes()}


@pytest.mark.slow
def test_eval_with_workers_equals_one_process(reference_set, slow_dataset, capsys):
    argv = ["eval", slow_dataset, "--rig", reference_set / "rig.yaml", "--texcoords", reference_set / "tc",
            "--poses", "0:12", "--json", "--quiet"]
    code, one, err = run(capsys, *argv)
    assert code == 0, err
    code, two, err = run(capsys, *argv, "--workers", "2")
    assert code == 0, err
    assert one == two and json.loads(one)["num_images"] == 24


@pytest.mark.slow
def test_dask_local_cluster_slide_equals_one_process(tmp_path, reference_set, slow_dataset):
    distributed = pytest.importorskip("dask.distributed")
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions

    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        slide_dataset(slow_dataset, reference_set / "rig.yaml", tmp_path / "tc", poses=list(range(40)),
                      options=SlideOptions(subdiv=0),
                      scheduler=cluster.scheduler_address, progress=False)
    ref = tree(reference_set / "tc")  # the manifests too: the same files
    assert tree(tmp_path / "tc") == ref


@pytest.mark.slow
def test_dask_worker_with_threads_slides_and_evaluates_like_one_process(tmp_path, reference_set, slow_dataset):
    """`dask worker` runs several tasks at once in threads of one process: each thread
    needs its own GL context and state (a shared one crashed or mixed results). Slide,
    eval and views."""
    distributed = pytest.importorskip("dask.distributed")
    from mvtex.evaluation.evaluate import evaluate
    from mvtex.sliding.dataset import slide_dataset
    from mvtex.sliding.options import SlideOptions

    rig = reference_set / "rig.yaml"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=4, processes=True, dashboard_address=None) as cluster:
        slide_dataset(slow_dataset, rig, tmp_path / "tc", poses=list(range(40)), options=SlideOptions(subdiv=0),
                      scheduler=cluster.scheduler_address, progress=False)
        threaded = evaluate(slow_dataset, rig, tmp_path / "tc", poses=list(range(0, 40, 2)),
                            scheduler=cluster.scheduler_address, progress=False)
        views = ["views", slow_dataset, "--rig", rig, "--texcoords", tmp_path / "tc", "--between", "a,b", "--steps", 3,
                 "--method", "blend", "--poses", "0:12", "--quiet"]
        assert main([str(a) for a in views + ["--out", tmp_path / "v", "--scheduler", cluster.scheduler_address]]) == 0
    assert main([str(a) for a in views + ["--out", tmp_path / "v1"]]) == 0
    assert tree(tmp_path / "v") == tree(tmp_path / "v1")
    ref = tree(reference_set / "tc")  # the manifests too: the same files
    assert tree(tmp_path / "tc") == ref
    assert threaded == evaluate(slow_dataset, rig, reference_set / "tc", poses=list(range(0, 40, 2)), progress=False)


def test_an_input_error_in_a_worker_process_reaches_the_command_intact():
    """InputError pickles by (path, problem), so a worker's error is the caller's."""
    from mvtex.util.parallel import map_unordered

    err = pickle.loads(pickle.dumps(InputError("a/b.npy", "NaN  at\nrow 3")))
    assert (err.path, err.problem, str(err)) == ("a/b.npy", "NaN at row 3", "a/b.npy: NaN at row 3")
    with pytest.raises(InputError, match=r"^file\d\.npy: problem \d$"):
        list(map_unordered(bad_input, [(i,) for i in range(4)], workers=2))


def test_nan_in_the_targets_of_parallel_views_and_training_exits_2_before_any_work(tmp_path, slid_sheet0, tiny_dataset,
                                                                                    capsys):
    pytest.importorskip("torch")
    tc = copy_set(slid_sheet0, tmp_path)
    d = np.load(tc / "a" / "displacement.npy")
    d[1, 2, 0] = np.nan
    np.save(tc / "a" / "displacement.npy", d)
    rig = slid_sheet0.parent / "rig.yaml"
    for argv, out in ((["views", tiny_dataset, "--rig", rig, "--texcoords", tc, "--between", "a,b", "--steps", 2,
                        "--method", "blend"], tmp_path / "v"),
                      (["train", tiny_dataset, "--texcoords", tc, "--cameras", "b,a", "--arch", "gp"], tmp_path / "m")):
        code, _, err = run(capsys, *argv, "--out", out, "--workers", 2, "--quiet")
        one_line_error(code, err, "displacement.npy", "NaN")
        assert not out.exists()


@pytest.mark.parametrize("backend", ["here", "processes", "dask"])
def test_map_unordered_returns_every_task_once(backend):
    from mvtex.util.parallel import map_unordered

    tasks = [(i,) for i in range(23)]  # more than the tasks kept in flight
    if backend == "dask":
        distributed = pytest.importorskip("dask.distributed")
        with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                      dashboard_address=None) as cluster:
            results = list(map_unordered(square, tasks, scheduler=cluster.scheduler_address, max_in_flight=4))
    else:
        results = list(map_unordered(square, tasks, workers=1 if backend == "here" else 2, max_in_flight=4))
    assert sorted(results) == [i * i for i in range(23)]


def test_slide_refuses_to_finish_when_a_backend_loses_tasks(tmp_path, tiny_dataset, front_rig, monkeypatch, gl):
    import mvtex.sliding.dataset
    import mvtex.util.parallel

    real = mvtex.util.parallel.map_unordered

    def lossy(fn, tasks, **kw):
        return real(fn, list(tasks)[1:], **kw)

    monkeypatch.setattr(mvtex.sliding.dataset, "map_unordered", lossy)
    with pytest.raises(RuntimeError, match="were not computed"):
        _slide(tiny_dataset, front_rig, tmp_path / "tc")
    assert not (tmp_path / "tc").exists() and (tmp_path / "tc.partial").is_dir()


def test_camera_names_from_a_colmap_model_are_checked(tmp_path):
    pytest.importorskip("pycolmap")
    from mvtex.data.camera import look_at
    from mvtex.formats.colmap import read_rig, rig_reconstruction
    from mvtex.util.errors import InputError

    rec, ids = rig_reconstruction(Rig((look_at("a", (0, 0, 1), (0, 0, 0), width=64, height=48, focal=50.0),)))
    rec.images[ids["a"]].name = "bad name.png"
    rec.write_binary(str(tmp_path))
    with pytest.raises(InputError, match="camera name 'bad name' is not allowed"):
        read_rig(tmp_path)


def test_eval_heatmaps_do_not_go_into_a_foreign_folder(tmp_path, slid_sheet0, tiny_dataset, rig_file, capsys):
    heat = foreign(tmp_path)
    argv = ["eval", tiny_dataset, "--rig", rig_file, "--texcoords", slid_sheet0, "--poses", "0", "--heatmaps", heat, "--quiet"]
    code, _, err = run(capsys, *argv)
    one_line_error(code, err, heat, "--overwrite")
    assert tree(heat) == {"keep.txt": b"x"}
    code, _, err = run(capsys, *argv[:-3], "--heatmaps", tmp_path / "h", "--quiet")
    assert code == 0, err
    assert sorted(p.name for p in (tmp_path / "h").iterdir()) == [MARKER, "pose_00000_a.png", "pose_00000_b.png"]


@pytest.mark.parametrize("content,needle", [(b"\x93NUMPY garbage", "not a readable .npy"),
                                            (b"1 2\n3 nan\n", "NaN or infinite"), (b"1 2\n3\n", "cannot read poses")])
def test_import_pose_files(content, needle, tmp_path, capsys):
    from helpers import grid_mesh, write_obj

    faces, uv, rest = grid_mesh(4, 4)
    for k in range(2):
        write_obj(tmp_path / f"g{k}.obj", rest, uv, faces)
    poses = tmp_path / ("poses.npy" if content.startswith(b"\x93") else "poses.txt")
    poses.write_bytes(content)
    code, _, err = run(capsys, "import", "--out", tmp_path / "ds", "--gt", tmp_path / "g*.obj", "--inferred",
                       tmp_path / "g*.obj", "--pose-vectors", poses, "--quiet")
    one_line_error(code, err, poses, needle)
    assert not (tmp_path / "ds").exists()


@pytest.mark.slow
@pytest.mark.parametrize("command", ["import", "render", "triangulate", "predict"])
def test_every_writer_marks_its_output_and_may_replace_it(command, tmp_path, tiny_dataset, rig_file, slid_sheet0, capsys):
    out = tmp_path / "out"
    if command == "import":
        from helpers import grid_mesh, write_obj

        faces, uv, rest = grid_mesh(4, 4)
        write_obj(tmp_path / "g.obj", rest, uv, faces)
        argv = ["import", "--out", out, "--gt", tmp_path / "*.obj", "--inferred", tmp_path / "*.obj"]
    elif command == "render":
        argv = ["render", tiny_dataset, "--rig", rig_file, "--pose", 0, "--out", out]
    elif command == "triangulate":
        argv = ["triangulate", tiny_dataset, "--rig", rig_file, "--texcoords", slid_sheet0, "--pose", 0, "--out", out]
    else:
        pytest.importorskip("torch")
        argv = ["predict", tiny_dataset, "--model", fake_model(tmp_path / "m", tiny_dataset), "--out", out,
                "--poses", "0:2"]
    for _ in range(2):
        code, _, err = run(capsys, *argv, "--quiet")
        assert code == 0, err
        assert json.loads((out / MARKER).read_text())["command"] == command
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def _lying_npy(array: np.ndarray, shape: tuple) -> bytes:
    """The bytes of `array` saved as .npy, with a header that declares `shape`."""
    import io as bytes_io

    from numpy.lib import format as npformat

    buf = bytes_io.BytesIO()
    npformat.write_array_header_1_0(buf, {"descr": npformat.dtype_to_descr(array.dtype), "fortran_order": False,
                                          "shape": shape})
    return buf.getvalue() + np.ascontiguousarray(array).tobytes()


def test_huge_declared_sizes_are_refused_before_allocation(tmp_path, tiny_dataset, rig_file, capsys):
    import zipfile

    ds = tmp_path / "ds"
    shutil.copytree(tiny_dataset, ds)
    gt = np.load(ds / "gt.npy")
    (ds / "gt.npy").write_bytes(_lying_npy(gt, (10**9,) + gt.shape[1:]))
    code, _, err = run(capsys, "slide", ds, "--rig", rig_file, "--out", tmp_path / "tc", "--quiet")
    one_line_error(code, err, ds / "gt.npy", "not a readable .npy")

    shutil.rmtree(ds)
    shutil.copytree(tiny_dataset, ds)
    with np.load(ds / "mesh.npz") as z:
        mesh = {k: z[k] for k in z.files}
    with zipfile.ZipFile(ds / "mesh.npz", "w") as archive:  # uv declares 10^12 rows, holds 480
        for key, value in mesh.items():
            archive.writestr(f"{key}.npy", _lying_npy(value, (10**12, 2)) if key == "uv" else _lying_npy(value, value.shape))
    t0 = time.perf_counter()
    code, _, err = run(capsys, "slide", ds, "--rig", rig_file, "--out", tmp_path / "tc", "--quiet")
    one_line_error(code, err, ds / "mesh.npz", "declares shape (1000000000000, 2)")
    assert time.perf_counter() - t0 < 10


@pytest.mark.slow
def test_two_slides_on_one_output_the_second_is_refused(tmp_path, slow_dataset, reference_set, capsys):
    out = tmp_path / "tc"
    argv = MVTEX + ["slide", str(slow_dataset), "--rig", str(reference_set / "rig.yaml"), "--out", str(out),
                    "--subdiv", "0", "--workers", "1", "--quiet"]
    proc = subprocess.Popen(argv, stderr=subprocess.PIPE)
    try:
        _wait_for_progress(tmp_path / "tc.partial", proc)
        code, _, err = run(capsys, *argv[3:])
        one_line_error(code, err, out, f"in use by pid {proc.pid}")
    finally:
        assert proc.wait(timeout=300) == 0, proc.stderr.read()
    assert tree(out) == tree(reference_set / "tc") | {MARKER: (out / MARKER).read_bytes()}


def test_a_symlink_at_out_is_refused(tmp_path, capsys):
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    code, _, err = run(capsys, "synth", "--out", tmp_path / "link", "--num-poses", 10)
    one_line_error(code, err, "symbolic link")


def test_evicting_cached_render_targets_leaves_no_gl_error(gl, sheet):
    """More image sizes than the context keeps render targets for: releasing the oldest
    must not leave GL pointing at a released framebuffer (the next draw would report an
    error)."""
    from mvtex.data.camera import look_at
    from mvtex.render.raster import rasterize

    faces, uv, rest = sheet
    assert gl.error == "GL_NO_ERROR"
    for k in range(12):
        camera = look_at("c", (0, 0, 1.2), (0, 0, 0), width=40 + k, height=30, focal=60.0)
        raster = rasterize(gl, rest, faces, camera)
        assert raster.tri_id.shape == (30, 40 + k)
        assert gl.error == "GL_NO_ERROR", k
