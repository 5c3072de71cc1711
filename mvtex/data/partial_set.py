"""The resumable writer of texcoord sets (`slide`, `views`): a set written row by row into
``OUT.partial`` and renamed to OUT when every row is in."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from mvtex.data.texcoord_header import TexcoordHeader
from mvtex.data.texcoords import LAYOUT, RIG_FILE, write_header
from mvtex.util.errors import InputError
from mvtex.util.files import create_npy, load_npy, save_npy, write_npy_rows
from mvtex.util.output import (
    atomic_path,
    foreign_entries,
    forget,
    mark_output,
    remove_leftovers,
    replace_path,
    written_by_mvtex,
)


class PartialSet:
    """A texcoord set written row by row into ``OUT.partial`` and renamed to OUT when every
    row is in: the resumable writer of `slide` and `views`.

    Opening keeps an unfinished set of the same run (its texcoords.json holds the same poses,
    cameras, subdiv and `record` values) and continues from its done masks; another run's
    is deleted and started over (said on stderr); a folder that is not an unfinished set of
    this command is refused. Rows go through the files (positioned writes, then fsync), so
    they are on disk before a camera's done mask (``<camera>/done.npy``) says so; a kill
    loses at most the rows in flight.

    Args:
        out: the finished set's directory.
        command: the command writing it, for messages ("slide").
        source_prefix: how the set's "source" starts ("ts", "views-"): what an unfinished set
            of this command looks like.
        faces, uv, parent, source, subdiv, poses, cameras: the set's header (`write_header`).
        record: the other keys of texcoords.json, compared with an unfinished set's
            (JSON-like values: lists, not tuples).

    Raises:
        InputError: OUT.partial exists and is not an unfinished set of `command`, or its
            arrays do not have the set's shapes.
    """

    def __init__(self, out: str | os.PathLike, command: str, source_prefix: str, *, faces: np.ndarray,
                 uv: np.ndarray, parent: np.ndarray, source: str, subdiv: int, poses: Sequence[int],
                 cameras: Sequence[str], record: dict[str, Any]):
        self.out = Path(out)
        self.path = self.out.with_name(self.out.name + ".partial")
        self.poses = [int(p) for p in poses]
        self.cameras = list(cameras)
        self._open(command, source_prefix, faces=faces, uv=uv, parent=parent, source=source, subdiv=subdiv,
                   record=record)
        shape = (len(self.poses), len(uv))
        self.done: dict[str, np.ndarray] = {}
        for cam in self.cameras:
            # A run killed while saving a done mask leaves the mask's hidden temporary and aside
            # copies: they must not end up in the finished set. No mask (a run stopped while
            # finishing): that camera is done again.
            remove_leftovers(self.path / cam, "done.npy")
            mask = self.path / cam / "done.npy"
            self.done[cam] = np.array(load_npy(mask, mmap=False), dtype=bool) if mask.is_file() else np.zeros(shape[0], bool)
            d, a = (load_npy(self.path / cam / name) for name in ("displacement.npy", "assigned.npy"))
            if d.shape != shape + (2,) or a.shape != shape or self.done[cam].shape != shape[:1]:
                raise InputError(self.path / cam, "unfinished result has unexpected array shapes; delete it and rerun")
            del d, a

    def _open(self, command: str, source_prefix: str, *, faces, uv, parent, source, subdiv, record) -> None:
        partial = self.path
        header = TexcoordHeader(source=source, subdiv=subdiv, poses=self.poses, cameras=self.cameras, record=record)
        if partial.is_dir():
            old = TexcoordHeader.peek(partial)
            if old is None or not old.source.startswith(source_prefix):
                raise InputError(partial, f"exists and is not an unfinished mvtex {command}; move it away and rerun")
            if header.same_run(old):
                return
            # Only what mvtex wrote there goes: its manifest's entries (and the views' rig.yaml,
            # saved last), or, for a partial from before manifests, the set's own layout.
            if written_by_mvtex(partial) is not None:
                foreign = [e for e in foreign_entries(partial) if e != RIG_FILE]
            else:
                layout = list(old.cameras) + LAYOUT
                foreign = [e for e in foreign_entries(partial) if e.split("/")[0] not in layout]
            if foreign:
                raise InputError(partial, f"an unfinished run with other settings that also holds files mvtex did "
                                 f"not write ({', '.join(foreign[:3])}); move them away and rerun")
            print(f"{partial}: an unfinished run with other settings; starting over", file=sys.stderr)
            shutil.rmtree(partial)
        # Built in a stamped temporary beside it, marked as `command`'s, renamed in whole.
        with atomic_path(partial) as tmp:
            tmp.mkdir()
            write_header(tmp, faces=faces, uv=uv, parent=parent, source=header.source, subdiv=header.subdiv,
                         poses=header.poses, cameras=header.cameras, **header.record)
            for cam in self.cameras:
                (tmp / cam).mkdir()
                create_npy(tmp / cam / "displacement.npy", np.float32, (len(self.poses), len(uv), 2))
                create_npy(tmp / cam / "assigned.npy", np.bool_, (len(self.poses), len(uv)))
                np.save(tmp / cam / "done.npy", np.zeros(len(self.poses), bool), allow_pickle=False)
            mark_output(tmp, command)

    @property
    def rows_done(self) -> int:
        """(pose, camera) rows already in."""
        return int(sum(mask.sum() for mask in self.done.values()))

    def todo(self, camera: str) -> list[int]:
        """Rows (indices into `poses`) of `camera` still to compute."""
        return np.flatnonzero(~self.done[camera]).tolist()

    def write(self, camera: str, rows: Sequence[int], displacement: np.ndarray, assigned: np.ndarray) -> None:
        """Write rows of one camera ((r,n',2) float32 and (r,n') bool), then mark them done."""
        rows = list(rows)
        write_npy_rows(self.path / camera / "displacement.npy", rows, displacement)
        write_npy_rows(self.path / camera / "assigned.npy", rows, assigned)
        self.done[camera][rows] = True
        save_npy(self.path / camera / "done.npy", self.done[camera])

    def finish(self) -> Path:
        """Rename the finished set to OUT (an older OUT aside first, deleted after), then drop
        the done masks: a stop in between leaves a resumable partial or a complete set.

        Raises:
            RuntimeError: rows still missing (a backend that lost tasks): never rename an
                incomplete set into place.
        """
        missing = [c for c in self.cameras if not self.done[c].all()]
        if missing:
            raise RuntimeError(f"{self.path}: {int((~self.done[missing[0]]).sum())} poses of camera {missing[0]!r} "
                               "were not computed; rerun to finish them")
        replace_path(self.path, self.out)
        for cam in self.cameras:
            (self.out / cam / "done.npy").unlink(missing_ok=True)
        forget(self.out, [f"{cam}/done.npy" for cam in self.cameras])
        return self.out
