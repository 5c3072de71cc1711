"""File-system states a writer meets in a shared folder, for the hypothesis fuzz of the
writer policy (tests/util/test_writer_policy.py through the API, tests/cli/test_fuzz.py
through the command line): links planted at the names of mvtex's lock, manifest and stamps,
a user's files named like mvtex's transients, links and bind mounts inside an output.

`plant` makes one state around an output path; `Planted.check` then asserts what the
writer policy promises whatever it did: nothing planted (and nothing a link points to)
changed or went away, and no transient of mvtex's was left beside the output.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

from hypothesis import strategies as st

MARKER = ".mvtex-output.json"

# (kind, where): where "beside" plants next to the output, "inside" in it, "deep" in a
# folder of it (when the output exists and has one).
KINDS = ["lock-link", "lock-hardlink", "lock-file", "manifest-link", "manifest-link-victim", "manifest-tmp",
         "manifest-tmp-link", "stamp-link", "user-temporary", "dir-link", "file-link", "user-file-like-lock",
         "bind", "out-link"]
planting = st.tuples(st.sampled_from(KINDS), st.sampled_from(["beside", "inside", "deep"]))
state = st.fixed_dictionaries({"out": st.sampled_from(["absent", "written", "empty"]),
                               "plantings": st.lists(planting, min_size=1, max_size=3),
                               "overwrite": st.booleans()})


def snapshot(path: Path) -> dict[str, object]:
    """Everything under `path` (links not followed): relative path -> bytes, ("link",
    target) or "dir"."""
    out: dict[str, object] = {}
    if os.path.islink(path):
        return {".": ("link", os.readlink(path))}
    if not path.exists():
        return {}
    for root, dirs, files in os.walk(path):
        for name in dirs + files:
            p = Path(root) / name
            rel = p.relative_to(path).as_posix()
            if p.is_symlink():
                out[rel] = ("link", os.readlink(p))
            elif p.is_dir():
                out[rel] = "dir"
            else:
                out[rel] = p.read_bytes()
    return out


def bind_mounts_allowed(scratch: Path) -> bool:
    """Whether this machine lets us bind-mount a folder (root, a mount command, no sandbox)."""
    if not shutil.which("mount"):
        return False
    source, target = scratch / "bind-source", scratch / "bind-target"
    source.mkdir(parents=True, exist_ok=True)
    target.mkdir(parents=True, exist_ok=True)
    ok = subprocess.run(["mount", "--bind", str(source), str(target)], capture_output=True).returncode == 0
    if ok:
        subprocess.run(["umount", str(target)], check=True)
    shutil.rmtree(source)
    shutil.rmtree(target)
    return ok


@dataclass
class Planted:
    """What `plant` made: the paths the writer must leave exactly as they are."""

    root: Path
    out: Path
    kept: dict[Path, dict] = field(default_factory=dict)  # planted path -> its snapshot
    mounts: list[Path] = field(default_factory=list)

    def keep(self, path: Path) -> None:
        self.kept[path] = snapshot(path) if path.is_dir() and not path.is_symlink() else \
            ({".": ("link", os.readlink(path))} if path.is_symlink() else {".": path.read_bytes()})

    def check(self) -> None:
        for path, before in self.kept.items():
            if path.is_symlink():
                now = {".": ("link", os.readlink(path))}
            elif path.is_dir():
                now = snapshot(path)
            elif path.exists():
                now = {".": path.read_bytes()}
            else:
                now = None
            assert now == before, f"{path} changed or went away"
        hidden = [p.name for p in self.out.parent.iterdir() if p.name.startswith(f".{self.out.name}.")
                  and p not in self.kept]
        assert not hidden, f"left beside the output: {hidden}"

    def unmount(self) -> None:
        for target in reversed(self.mounts):
            subprocess.run(["umount", str(target)], check=True)
        self.mounts.clear()


def plant(root: Path, out: Path, plantings, *, binds: bool) -> Planted:
    """Plant `plantings` ((kind, where) pairs, `KINDS`) around output `out` (its parent is
    `root`-relative scratch space). Victims (what links point to) live in root/victims."""
    victims = root / "victims"
    victims.mkdir(exist_ok=True)
    victim_file = victims / "victim.txt"
    if not victim_file.exists():
        victim_file.write_text("a victim: nothing may write through a link to it\n")
    victim_dir = victims / "folder"
    if not victim_dir.exists():
        victim_dir.mkdir()
        (victim_dir / "precious.txt").write_text("precious\n")
    other = victims / "other-output"
    if not other.exists():  # a manifest of another output that lists names a user's file may have
        other.mkdir()
        (other / MARKER).write_text('{"command": "synth", "files": ["notes.txt", "a", "a/notes.txt"]}\n')
    done = Planted(root, out)
    done.keep(victims)
    try:
        _plant(done, plantings, victim_file, victim_dir, other, binds)
    except BaseException:
        done.unmount()
        raise
    return done


def _plant(done: Planted, plantings, victim_file: Path, victim_dir: Path, other: Path, binds: bool) -> None:
    out = done.out
    for i, (kind, where) in enumerate(plantings):
        if where == "beside" or not out.is_dir() or out.is_symlink():
            folder, name = out.parent, out.name
        elif where == "deep":
            subs = sorted(p for p in out.iterdir() if p.is_dir() and not p.is_symlink() and not p.name.startswith(".")
                          and p not in done.mounts)
            folder, name = (subs[0] if subs else out), f"x{i}"
        else:
            folder, name = out, f"x{i}"
        inside = folder != out.parent
        if kind == "lock-link":
            path = folder / f".{name}.mvtex-lock"
            if not os.path.lexists(path):
                path.symlink_to(victim_file)
        elif kind == "lock-hardlink":
            path = folder / f".{name}.mvtex-lock"
            if not os.path.lexists(path):
                os.link(victim_file, path)
        elif kind in ("lock-file", "user-file-like-lock"):
            path = folder / (f".{name}.mvtex-lock" if kind == "lock-file" else f".{name}.mvtex-lock.bak")
            if not os.path.lexists(path):
                path.write_text("my notes, not a lock\n")
        elif kind in ("manifest-link", "manifest-link-victim") and inside:
            path = folder / MARKER
            if os.path.lexists(path):
                os.unlink(path)
            path.symlink_to(other / MARKER if kind == "manifest-link" else victim_file)
            note = folder / "notes.txt"
            if not os.path.lexists(note):
                note.write_text("a user's file of a name that manifest lists\n")
                done.keep(note)
        elif kind in ("manifest-tmp", "manifest-tmp-link"):
            path = folder / f"{MARKER}.tmp"
            if os.path.lexists(path):
                continue
            if kind == "manifest-tmp":
                path.write_text("a user's file\n")
            else:
                path.symlink_to(victim_file)
        elif kind in ("stamp-link", "user-temporary"):
            path = folder / f".{name}.mvtex-abcd{i:04d}.tmp"
            if os.path.lexists(path):
                continue
            path.mkdir()
            (path / "keep.txt").write_text("keep\n")
            if kind == "stamp-link":
                (path / ".mvtex-temporary").symlink_to(victim_file)
        elif kind in ("dir-link", "file-link") and inside:
            path = folder / f"link{i}"
            path.symlink_to(victim_dir if kind == "dir-link" else victim_file)
        elif kind == "bind" and inside and binds:
            path = folder / f"mnt{i}"
            path.mkdir()
            subprocess.run(["mount", "--bind", str(victim_dir), str(path)], check=True)
            done.mounts.append(path)
        elif kind == "out-link" and not os.path.lexists(out):
            out.symlink_to(victim_dir, target_is_directory=True)
            path = out
        else:
            continue
        done.keep(path)
