"""texcoords.json, the header of a texcoord set (DESIGN §4): the one place it is written and
read.

    {"format": "mvtex-texcoords", "version": 1, "source": "ts"|"tsnn"|"views-blend"|...,
     "subdiv": s, "poses": [...], "cameras": [...], ...what the set was made from}

`TexcoordHeader` holds it. Made in Python, a bad value is an `OptionError` naming the field;
read from a file (`TexcoordHeader.read`), an `InputError` naming the file and the key.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from mvtex.data.camera import check_camera_name
from mvtex.data.limits import MAX_SUBDIV
from mvtex.util.errors import InputError, OptionError
from mvtex.util.files import dumps_strict, read_header

FORMAT = "mvtex-texcoords"
VERSION = 1
FILE = "texcoords.json"

_KEYS = ("format", "version", "source", "subdiv", "poses", "cameras")


def _integer(value) -> bool:
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def _problems(source, subdiv, poses, cameras, record, num_poses: int | None = None) -> Iterator[tuple[str, str]]:
    """(key, problem) for every value of a header that is not what the format allows."""
    if not isinstance(source, str) or not source:
        yield "source", f'must be a non-empty string ("ts", "tsnn", ...), got {source!r}'
    if not _integer(subdiv) or not 0 <= subdiv <= MAX_SUBDIV:
        yield "subdiv", f"must be an integer in 0..{MAX_SUBDIV}, got {subdiv!r}"
    if not isinstance(poses, (list, tuple)) or not poses:
        yield "poses", f"must be a non-empty list of pose indices, got {poses!r:.60}"
    elif not all(_integer(p) for p in poses):
        yield "poses", "must be a list of integer pose indices"
    else:
        bad = [p for p in poses if p < 0 or (num_poses is not None and p >= num_poses)]
        if bad:
            limit = f"[0, {num_poses})" if num_poses is not None else "non-negative"
            yield "poses", f"pose index {bad[0]} out of range ({limit})"
        elif len(set(int(p) for p in poses)) != len(poses):
            yield "poses", "lists a pose twice"
    if not isinstance(cameras, (list, tuple)) or not cameras:
        yield "cameras", f"must be a non-empty list of camera names, got {cameras!r:.60}"
    else:
        for name in cameras:
            try:
                check_camera_name(name)
            except ValueError as err:
                yield "cameras", str(err)
                return
        if len({c.lower() for c in cameras}) != len(cameras):
            yield "cameras", "names a camera twice (ignoring case)"
    if not isinstance(record, Mapping) or any(not isinstance(k, str) or k in _KEYS for k in record):
        yield "record", f"must be a dict of other keys than {', '.join(_KEYS)}"


@dataclass(frozen=True)
class TexcoordHeader:
    """The header of a texcoord set.

    Attributes:
        source: what made the set: "ts" (slide), "tsnn" (predict), "views-blend", ...
        subdiv: subdivision level of the set's mesh, 0..MAX_SUBDIV.
        poses: the dataset pose index of each row of the per-camera arrays (distinct, >= 0).
        cameras: the per-camera folders (checked camera names, unique ignoring case).
        record: every other key: what the set was made from ("dataset", "rig",
            "options", ...), JSON values.

    Raises:
        OptionError: naming the field whose value the format does not allow.
    """

    source: str
    subdiv: int
    poses: tuple[int, ...]
    cameras: tuple[str, ...]
    record: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        for key, problem in _problems(self.source, self.subdiv, self.poses, self.cameras, self.record):
            raise OptionError(key, f"{problem}")
        object.__setattr__(self, "subdiv", int(self.subdiv))
        object.__setattr__(self, "poses", tuple(int(p) for p in self.poses))
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "record", dict(self.record))

    def to_json(self) -> dict[str, Any]:
        """texcoords.json as a dict."""
        return {"format": FORMAT, "version": VERSION, "source": self.source, "subdiv": self.subdiv,
                "poses": list(self.poses), "cameras": list(self.cameras), **self.record}

    def write(self, directory: str | os.PathLike) -> Path:
        """Write texcoords.json into `directory` (a set being built: the caller renames it in)."""
        path = Path(directory) / FILE
        path.write_text(dumps_strict(self.to_json(), indent=2) + "\n")
        return path

    @classmethod
    def from_json(cls, meta: Any, source: str | os.PathLike, num_poses: int | None = None) -> TexcoordHeader:
        """The header of a texcoords.json's content, checked.

        Args:
            meta: the file's JSON.
            source: the file, for messages.
            num_poses: the dataset's pose count: every pose must be below it.

        Raises:
            InputError: naming `source` and the key.
        """
        if not isinstance(meta, dict) or meta.get("format") != FORMAT:
            raise InputError(source, f'not a texcoord set (format must be "{FORMAT}")')
        if meta.get("version") != VERSION:
            raise InputError(source, f"unsupported version {meta.get('version')!r} (expected {VERSION})")
        values = (meta.get("source", "unknown"), meta.get("subdiv", 0), meta.get("poses"), meta.get("cameras"))
        record = {k: v for k, v in meta.items() if k not in _KEYS}
        for key, problem in _problems(*values, record, num_poses):
            raise InputError(source, f"'{key}' {problem}")
        return cls(*values, record)

    @classmethod
    def read(cls, directory: str | os.PathLike, num_poses: int | None = None) -> TexcoordHeader:
        """The header of the texcoord set in `directory` (`from_json` of its texcoords.json).

        Raises:
            InputError: no such folder, no readable texcoords.json, or a value the format
                does not allow (naming the file and the key).
        """
        return cls.from_json(read_header(directory, FILE, FORMAT, VERSION, "a texcoord set"),
                             Path(directory) / FILE, num_poses)

    @classmethod
    def peek(cls, directory: str | os.PathLike) -> TexcoordHeader | None:
        """The header of `directory` when it holds a readable one, else None (for a writer
        deciding whether a folder is its own unfinished set)."""
        try:
            return cls.read(directory)
        except InputError:
            return None

    def same_run(self, other: TexcoordHeader | None) -> bool:
        """Whether `other` is the header of a set made with these poses, cameras, subdivision,
        source and record (JSON values compared as texcoords.json holds them)."""
        return other is not None and json.loads(dumps_strict(self.to_json())) == json.loads(dumps_strict(other.to_json()))
