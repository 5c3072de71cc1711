"""The writer policy (`mvtex.util.output`) through the public API (`import mvtex`): a writer
never removes what mvtex did not write, never writes into an input, cleans only its own
stamped temporaries, and names its output when the disk is full. The same kinds through the
command line are in tests/cli/test_writer_policy_cli.py."""

from __future__ import annotations

import errno
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

import mvtex
from mvtex.util.output import MARKER


def tree(path: Path) -> dict[str, bytes]:
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def small_arrays(sheet):
    faces, uv, rest = sheet
    gt = np.stack([rest, rest + 0.001]).astype(np.float32)
    return dict(faces=faces, uv=uv, gt=gt, inferred=gt.copy(), poses=np.zeros((2, 1), np.float32))


def texcoord_arrays(sheet):
    faces, uv, _ = sheet
    parent = np.stack([np.arange(len(uv))] * 2, axis=1)
    return dict(faces=faces, uv=uv, parent=parent, source="ts", subdiv=0, poses=[0],
                displacement={"a": np.zeros((1, len(uv), 2), np.float32)},
                assigned={"a": np.ones((1, len(uv)), bool)})


# -- never remove what mvtex did not write ------------------------------------------------------

def test_a_rerun_keeps_a_file_the_user_put_into_the_output(tmp_path, sheet):
    out = tmp_path / "ds"
    mvtex.save_dataset(out, **small_arrays(sheet))
    (out / "notes.txt").write_text("my notes")
    before = tree(out)
    with pytest.raises(mvtex.InputError, match="notes.txt"):
        mvtex.save_dataset(out, **small_arrays(sheet))
    with pytest.raises(mvtex.InputError, match="notes.txt"):
        mvtex.save_dataset(out, overwrite=True, **small_arrays(sheet))
    assert tree(out) == before


@pytest.mark.parametrize("writer", ["save_dataset", "save_texcoords", "write_synth"])
def test_library_writers_refuse_a_folder_they_did_not_write(writer, tmp_path, sheet):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "photo.jpg").write_bytes(b"\xff\xd8 a photo")
    call = {
        "save_dataset": lambda **kw: mvtex.save_dataset(out, **small_arrays(sheet), **kw),
        "save_texcoords": lambda **kw: mvtex.save_texcoords(out, **texcoord_arrays(sheet), **kw),
        "write_synth": lambda **kw: mvtex.write_synth(out, mvtex.SynthOptions(num_poses=10), **kw),
    }[writer]
    for overwrite in (False, True):
        with pytest.raises(mvtex.InputError, match="photo.jpg"):
            call(overwrite=overwrite)
    assert tree(out) == {"photo.jpg": b"\xff\xd8 a photo"}


def test_overwrite_replaces_another_writers_output_only(tmp_path, sheet):
    out = tmp_path / "out"
    mvtex.save_texcoords(out, **texcoord_arrays(sheet))
    with pytest.raises(mvtex.InputError, match="save_texcoords"):
        mvtex.save_dataset(out, **small_arrays(sheet))
    mvtex.save_dataset(out, overwrite=True, **small_arrays(sheet))
    marker = json.loads((out / MARKER).read_text())
    assert marker["command"] == "save_dataset"
    assert set(marker["files"]) == {p.relative_to(out).as_posix() for p in out.rglob("*")} - {MARKER}


def test_save_rig_replaces_a_file_only_with_overwrite(tmp_path, front_rig):
    path = tmp_path / "rig.yaml"
    path.write_text("my calibration\n")
    with pytest.raises(mvtex.InputError, match="exists"):
        mvtex.save_rig(front_rig, path)
    assert path.read_text() == "my calibration\n"
    mvtex.save_rig(front_rig, path, overwrite=True)
    assert mvtex.load_rig(path).names == front_rig.names


def test_temporaries_mvtex_did_not_make_survive(tmp_path, sheet):
    # Names like mvtex's temporaries, made by someone else (no stamp inside).
    lookalikes = [tmp_path / ".ds.backup.tmp", tmp_path / ".ds.mvtex-x.tmp", tmp_path / ".ds.old.aside"]
    for folder in lookalikes:
        folder.mkdir()
        (folder / "keep.txt").write_text("keep")
    out = tmp_path / "ds"
    mvtex.save_dataset(out, **small_arrays(sheet))
    mvtex.save_dataset(out, **small_arrays(sheet))  # its own output: replaced, leftovers cleaned
    for folder in lookalikes:
        assert (folder / "keep.txt").read_text() == "keep"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["ds"] + [f.name for f in lookalikes])


def test_own_killed_temporaries_are_cleaned(tmp_path, sheet):
    from mvtex.util.output import _temporary

    out = tmp_path / "ds"
    left = _temporary(out, "tmp")  # what a killed run leaves: named and stamped
    (left / "ds").mkdir()
    mvtex.save_dataset(out, **small_arrays(sheet))
    assert not left.exists()


# -- never write into an input -------------------------------------------------------------------

def test_slide_onto_or_into_its_dataset_is_refused(tmp_path, tiny_dataset, front_rig, gl):
    data = tmp_path / "data"
    shutil.copytree(tiny_dataset, data)
    before = tree(data)
    ds = mvtex.load_dataset(data)
    options = mvtex.SlideOptions(subdiv=0)
    for out, needle in ((data, "is also an input"), (data / "ts", "lies inside the input"),
                        (tmp_path, "contains the input")):
        with pytest.raises(mvtex.InputError, match=needle):
            mvtex.slide_dataset(ds, front_rig, out, poses=[0], options=options, progress=False, overwrite=True)
    assert tree(data) == before and not (tmp_path / "data.partial").exists()


def test_a_symlinked_output_path_into_the_input_is_refused(tmp_path, tiny_dataset, slid_sheet0):
    tc = tmp_path / "tc"
    shutil.copytree(slid_sheet0, tc)
    (tmp_path / "alias").symlink_to(tc)
    ds = mvtex.load_dataset(tiny_dataset)
    with pytest.raises(mvtex.InputError, match="input"):
        mvtex.train(ds, mvtex.open_texcoords(tc), tmp_path / "alias" / "model", camera="a", overwrite=True,
                    progress=False)
    assert not (tc / "model").exists()


def test_save_dataset_refuses_to_replace_the_files_it_reads(tmp_path, sheet):
    out = tmp_path / "ds"
    mvtex.save_dataset(out, **small_arrays(sheet))
    ds = mvtex.load_dataset(out)  # gt, inferred memory-mapped from out
    with pytest.raises(mvtex.InputError, match="input"):
        mvtex.save_dataset(out, faces=ds.faces, uv=ds.uv, gt=ds.gt, inferred=ds.inferred, poses=ds.poses)


def test_the_current_directory_is_never_an_output(tmp_path, sheet, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for out in (".", tmp_path, tmp_path.parent):
        with pytest.raises(mvtex.InputError, match="current directory"):
            mvtex.save_dataset(out, overwrite=True, **small_arrays(sheet))


# -- a full disk, a file-size limit ----------------------------------------------------------------

def test_a_full_disk_names_the_output_and_leaves_nothing(tmp_path, sheet, monkeypatch):
    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")  # no file name, as numpy's writes

    monkeypatch.setattr(np, "save", full)
    out = tmp_path / "ds"
    with pytest.raises(mvtex.OutputError, match=r"ds: cannot write it \(No space left on device\)"):
        mvtex.save_dataset(out, **small_arrays(sheet))
    assert list(tmp_path.iterdir()) == []


# -- render and demo -------------------------------------------------------------------------------

def test_a_failed_render_leaves_no_half_folder(tmp_path, tiny_dataset, front_rig, gl, monkeypatch):
    import mvtex.render.pose as render

    real, calls = render.save_png, []

    def save_then_die(path, image):
        calls.append(path)
        if len(calls) == 3:  # after the first camera's pictures
            raise KeyboardInterrupt
        return real(path, image)

    monkeypatch.setattr(render, "save_png", save_then_die)
    out = tmp_path / "render"
    with pytest.raises(KeyboardInterrupt):
        mvtex.render_pose(mvtex.load_dataset(tiny_dataset), front_rig, 0, out, progress=False, ctx=gl)
    assert list(tmp_path.iterdir()) == []


def test_a_demo_with_other_options_is_not_resumed(tmp_path, monkeypatch):
    import mvtex.synth.generate

    out = tmp_path / "demo"
    out.mkdir()
    (out / "demo.json").write_text(json.dumps({"options": {"num_poses": 10, "seed": 0, "tsnn": True},
                                               "mvtex": mvtex.__version__}))
    (out / MARKER).write_text(json.dumps({"command": "demo", "files": ["demo.json"]}))

    def no_work(*args, **kwargs):
        raise AssertionError("the demo started work instead of refusing")

    import mvtex.apps.demo  # the module that calls it

    monkeypatch.setattr(mvtex.apps.demo, "write_synth", no_work)
    with pytest.raises(mvtex.InputError, match="other options .*num_poses=10"):
        mvtex.run_demo(out, mvtex.DemoOptions(num_poses=12), progress=False)
    assert json.loads((out / "demo.json").read_text())["options"]["num_poses"] == 10


# -- links and lookalikes: only what mvtex made is mvtex's ------------------------------------------

@pytest.mark.parametrize("name", ["a/.notes.mvtex-lock", "a/.mvtex-output.json", "a/.mvtex-output.json.tmp",
                                  "a/.mvtex-output.json.abcd1234.tmp"])
def test_a_hidden_lookalike_deep_in_an_output_is_the_users(name, tmp_path, sheet):
    out = tmp_path / "tc"
    mvtex.save_texcoords(out, **texcoord_arrays(sheet))
    (out / name).write_text("the user's data, not mvtex's\n")
    before = tree(out)
    for overwrite in (False, True):
        with pytest.raises(mvtex.InputError, match="did not write"):
            mvtex.save_texcoords(out, overwrite=overwrite, **texcoord_arrays(sheet))
    assert tree(out) == before


def test_a_link_in_an_output_is_never_followed_and_never_mvtexs(tmp_path, sheet):
    out = tmp_path / "tc"
    mvtex.save_texcoords(out, **texcoord_arrays(sheet))
    elsewhere = tmp_path / "elsewhere.txt"
    elsewhere.write_text("keep")
    (out / "a" / "assigned.npy").unlink()
    (out / "a" / "assigned.npy").symlink_to(elsewhere)  # a listed name, now a link to someone's file
    with pytest.raises(mvtex.InputError, match=r"did not write \(a/assigned.npy\)"):
        mvtex.save_texcoords(out, overwrite=True, **texcoord_arrays(sheet))
    assert elsewhere.read_text() == "keep" and (out / "a" / "assigned.npy").is_symlink()


def test_a_writer_inside_an_output_claimed_with_overwrite_inherits_it(tmp_path, sheet):
    from mvtex.util.output import claim_output

    out = tmp_path / "out"
    with claim_output(out, "first", in_place=True):
        mvtex.save_texcoords(out / "tc", **texcoord_arrays(sheet))
    # Another command, with overwrite, writes in place: what the first wrote there is its to replace.
    with claim_output(out, "second", in_place=True, overwrite=True):
        mvtex.save_dataset(out / "tc", **small_arrays(sheet))
    assert json.loads((out / "tc" / MARKER).read_text())["command"] == "save_dataset"
    assert json.loads((out / MARKER).read_text())["command"] == "second"


# -- fuzz: the file-system states of a shared folder -------------------------------------------------

@pytest.fixture(scope="session")
def binds(tmp_path_factory) -> bool:
    from fs_states import bind_mounts_allowed

    return bind_mounts_allowed(tmp_path_factory.mktemp("bind-probe"))


def _fuzz_settings():
    from hypothesis import HealthCheck, settings

    return settings(max_examples=40, deadline=None, derandomize=True,
                    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


def test_writers_keep_the_policy_in_any_file_system_state(tmp_path_factory, sheet, front_rig, binds):
    """Links at the lock's, the manifest's and the stamps' names, a user's files named like
    them, links and bind mounts inside an output (where the machine allows them): a writer
    either writes or refuses with one line, and never changes, deletes or writes through
    anything it did not make."""
    from fs_states import plant, state
    from hypothesis import given
    from hypothesis import strategies as st

    @_fuzz_settings()
    @given(fs=state, which=st.sampled_from(["save_texcoords", "save_rig"]))
    def run(fs, which):
        root = tmp_path_factory.mktemp("fs")
        out = root / "work" / ("tc" if which == "save_texcoords" else "rig.yaml")
        out.parent.mkdir()

        def write(overwrite):
            if which == "save_texcoords":
                mvtex.save_texcoords(out, overwrite=overwrite, **texcoord_arrays(sheet))
            else:
                mvtex.save_rig(front_rig, out, overwrite=overwrite)

        if fs["out"] == "written":
            write(False)
        elif fs["out"] == "empty" and which == "save_texcoords":
            out.mkdir()
        planted = plant(root, out, fs["plantings"], binds=binds)
        try:
            try:
                write(fs["overwrite"])
            except mvtex.InputError as err:
                assert "\n" not in str(err) and str(out) in str(err), err
            else:
                if which == "save_texcoords":
                    assert mvtex.open_texcoords(out).cameras == ["a"]
                else:
                    assert mvtex.load_rig(out).names == front_rig.names
            planted.check()
        finally:
            planted.unmount()

    run()
