"""The demo's records, through `mvtex.cli.main(argv)` and the API: a demo folder is resumed
only when what it holds bears out the options its demo.json records, a refused run leaves
the folder byte for byte as it was (its manifest too), and the manifest of a folder written
in place lists what is there, never a temporary or an unfinished set's name."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from helpers import one_line_error, run

import mvtex
from mvtex.util.output import MARKER, claim_output


def tree(path: Path) -> dict[str, bytes]:
    return {p.relative_to(path).as_posix(): p.read_bytes() for p in sorted(path.rglob("*")) if p.is_file()}


def no_work(monkeypatch) -> None:
    """Any step of the pipeline after the dataset fails the test: the run had to refuse."""
    import mvtex.apps.demo  # the module that calls them (it imports them by name)

    def fail(*args, **kwargs):
        raise AssertionError("the demo started work instead of refusing")

    monkeypatch.setattr(mvtex.apps.demo, "write_synth", fail)
    monkeypatch.setattr(mvtex.apps.demo, "render_pose", fail)


@pytest.mark.slow
def test_an_edited_demo_json_does_not_make_a_run_another(tmp_path, capsys, monkeypatch):
    out = tmp_path / "demo"
    with claim_output(out, "demo", in_place=True):  # a 10-pose demo, stopped after its dataset
        mvtex.write_synth(out / "shirt", mvtex.SynthOptions(num_poses=10), progress=False)
        from mvtex.util.files import write_json

        write_json(out / "demo.json", {"options": {"num_poses": 10, "seed": 0, "tsnn": True},
                                       "mvtex": mvtex.__version__})
    record = json.loads((out / "demo.json").read_text())
    record["options"]["num_poses"] = 12  # edited by hand
    (out / "demo.json").write_text(json.dumps(record))
    before = tree(out)
    no_work(monkeypatch)
    code, _, err = run(capsys, "demo", "--out", out, "--num-poses", 12, "--quiet")
    one_line_error(code, err, out, "10 poses", "--overwrite")
    assert tree(out) == before


def test_a_refused_demo_leaves_its_folder_and_manifest_as_they_were(tmp_path, capsys, monkeypatch):
    out = tmp_path / "demo"
    out.mkdir()
    (out / "demo.json").write_text(json.dumps({"options": {"num_poses": 10, "seed": 0, "tsnn": True}}))
    (out / MARKER).write_text(json.dumps({"command": "demo", "files": ["demo.json"]}))
    before = tree(out)
    no_work(monkeypatch)
    code, _, err = run(capsys, "demo", "--out", out, "--num-poses", 12, "--quiet")
    one_line_error(code, err, out, "other options")
    assert tree(out) == before


@pytest.mark.gl
def test_a_manifest_written_in_place_lists_what_is_there(tmp_path, tiny_dataset, front_rig, gl):
    """A folder written in place (as the demo's) holding a resumable slide: its manifest
    lists the finished set, not the unfinished one's name it was written under or its
    done masks."""
    out = tmp_path / "demo"
    with claim_output(out, "demo", in_place=True):
        mvtex.slide_dataset(tiny_dataset, front_rig, out / "ts", poses=[0, 1], options=mvtex.SlideOptions(subdiv=0),
                            workers=1, progress=False, ctx=gl)
    listed = json.loads((out / MARKER).read_text())["files"]
    present = sorted(p.relative_to(out).as_posix() for p in out.rglob("*") if p.name != MARKER)
    assert sorted(listed) == present
    assert not any(".partial" in f or "done.npy" in f or ".mvtex-" in f for f in listed), listed
