"""The processed-session HDF5 schema (``processed.h5``; the simulator's ``ground_truth.h5``).

One table, :data:`FIELDS`, says every dataset's path, dtype and shape; the writer and the reader
both validate against it, so a file that loads is a file every later stage can use. Shapes use
symbols: T frames, V object vertices, F object faces. See DESIGN.md for the meaning of each key.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from couch import __version__
from couch.atomic import atomic_path
from couch.body.skeleton import CONTACT_NAMES, NUM_JOINTS

SCHEMA_VERSION = 1

INTERACTION_LABELS: dict[int, str] = {
    0: "locomotion", 1: "right hand", 2: "left hand", 3: "both hands", 4: "no hand contact",
    5: "free interaction",
}


class SchemaError(ValueError):
    """A processed-session file or object does not follow the schema (message names the file)."""


@dataclasses.dataclass(frozen=True)
class Field:
    path: str
    attr: str
    dtype: type | str
    shape: tuple[int | str, ...]


FIELDS: tuple[Field, ...] = (
    Field("/time", "time", np.float64, ("T",)),
    Field("/smpl/betas", "betas", np.float32, (10,)),
    Field("/smpl/global_orient", "global_orient", np.float32, ("T", 3)),
    Field("/smpl/body_pose", "body_pose", np.float32, ("T", 69)),
    Field("/smpl/transl", "transl", np.float32, ("T", 3)),
    Field("/joints", "joints", np.float32, ("T", NUM_JOINTS, 3)),
    Field("/object/name", "object_name", "str", ()),
    Field("/object/vertices", "object_vertices", np.float32, ("V", 3)),
    Field("/object/faces", "object_faces", np.int32, ("F", 3)),
    Field("/object/pose", "object_pose", np.float64, (4, 4)),
    Field("/object/frame_poses", "object_frame_poses", np.float64, ("T", 4, 4)),
    Field("/contacts/names", "contact_names", "str", (len(CONTACT_NAMES),)),
    Field("/contacts/active", "contact_active", np.bool_, ("T", len(CONTACT_NAMES))),
    Field("/contacts/points", "contact_points", np.float32, ("T", len(CONTACT_NAMES), 3)),
    Field("/labels/interaction", "interaction", np.int8, ("T",)),
)


@dataclasses.dataclass
class ProcessedSession:
    """One processed session in memory; attributes mirror :data:`FIELDS` (world frame, metres,
    seconds on the Kinect clock, axis-angle). ``quality`` holds ``/quality/*`` arrays by name."""

    session: str
    fps: float
    time: np.ndarray
    betas: np.ndarray
    global_orient: np.ndarray
    body_pose: np.ndarray
    transl: np.ndarray
    joints: np.ndarray
    object_name: str
    object_vertices: np.ndarray
    object_faces: np.ndarray
    object_pose: np.ndarray
    object_frame_poses: np.ndarray
    contact_active: np.ndarray
    contact_points: np.ndarray
    interaction: np.ndarray
    contact_names: tuple[str, ...] = CONTACT_NAMES
    quality: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    couch_version: str = __version__
    schema_version: int = SCHEMA_VERSION

    @property
    def num_frames(self) -> int:
        return len(self.time)

    @property
    def duration(self) -> float:
        """Seconds from the first to the last frame."""
        return float(self.time[-1] - self.time[0]) if len(self.time) else 0.0


def _check(where: str, f: Field, value: Any, sizes: dict[str, int]) -> None:
    """Check one value against its field, binding shape symbols (T, V, F) on first sight."""
    if f.dtype == "str":
        ok = isinstance(value, str) if f.shape == () else (
            len(value) == f.shape[0] and all(isinstance(v, str) for v in value))
        if not ok:
            want = "a string" if f.shape == () else f"{f.shape[0]} strings"
            raise SchemaError(f"{where}: '{f.path}' must be {want}, got {value!r}")
        return
    arr = np.asarray(value)
    if arr.ndim != len(f.shape):
        raise SchemaError(f"{where}: '{f.path}' has shape {arr.shape}, expected "
                          f"{_shape_str(f.shape, sizes)}")
    for dim, want in zip(arr.shape, f.shape, strict=True):
        if isinstance(want, str):
            want = sizes.setdefault(want, dim)
        if dim != want:
            raise SchemaError(f"{where}: '{f.path}' has shape {arr.shape}, expected "
                              f"{_shape_str(f.shape, sizes)}")
    kind_ok = (arr.dtype == np.bool_) if f.dtype is np.bool_ else (
        np.issubdtype(arr.dtype, np.integer) if np.issubdtype(f.dtype, np.integer)
        else np.issubdtype(arr.dtype, np.floating))
    if not kind_ok:
        raise SchemaError(f"{where}: '{f.path}' has dtype {arr.dtype}, expected "
                          f"{np.dtype(f.dtype).name}")


def _shape_str(shape: tuple[int | str, ...], sizes: dict[str, int]) -> str:
    return "(" + ", ".join(f"{d}={sizes[d]}" if d in sizes else str(d) for d in shape) + ")"


def validate(session: ProcessedSession, where: str = "ProcessedSession") -> None:
    """Raise :class:`SchemaError` unless every field has the schema's shape and dtype kind, the
    time stamps increase, and contact names and interaction labels are the schema's."""
    sizes: dict[str, int] = {}
    for f in FIELDS:
        _check(where, f, getattr(session, f.attr), sizes)
    if tuple(session.contact_names) != CONTACT_NAMES:
        raise SchemaError(f"{where}: '/contacts/names' is {list(session.contact_names)}, "
                          f"expected {list(CONTACT_NAMES)}")
    if np.any(np.diff(session.time) <= 0):
        bad = int(np.argmax(np.diff(session.time) <= 0)) + 1
        raise SchemaError(f"{where}: '/time' does not increase at frame {bad}")
    labels = np.asarray(session.interaction)
    if labels.size and (labels.min() < 0 or labels.max() > max(INTERACTION_LABELS)):
        raise SchemaError(f"{where}: '/labels/interaction' holds values outside 0..5")
    for name, arr in session.quality.items():
        if np.asarray(arr).dtype == object:
            raise SchemaError(f"{where}: quality '{name}' is not a numeric array")


def write_processed(path: str | os.PathLike, session: ProcessedSession) -> None:
    """Validate and write ``session`` to ``path`` atomically (temp file, then ``os.replace``).

    Per-frame arrays are chunked and gzip-compressed (with shuffle), as published datasets are.
    """
    path = Path(path)
    validate(session, str(path))
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        write_session_group(h5, session, validated=True)


def write_session_group(group: h5py.Group, session: ProcessedSession, *,
                        validated: bool = False) -> None:
    """Write ``session`` into an open HDF5 file or group: its attributes (``schema_version``,
    ``couch_version``, ``session``, ``fps``) and every :data:`FIELDS` key plus ``quality/*``
    relative to ``group`` (e.g. one group per sequence of an augmented dataset). Validates
    first unless ``validated``. Read back with :func:`read_session_group`."""
    if not validated:
        validate(session, f"{group.file.filename}:{group.name}")
    group.attrs["schema_version"] = SCHEMA_VERSION
    group.attrs["couch_version"] = session.couch_version
    group.attrs["session"] = session.session
    group.attrs["fps"] = float(session.fps)
    for f in FIELDS:
        key = f.path.lstrip("/")
        value = getattr(session, f.attr)
        if f.dtype == "str":
            group.create_dataset(key, data=value, dtype=h5py.string_dtype())
            continue
        arr = np.ascontiguousarray(value, dtype=f.dtype)
        big = arr.size >= 1024
        group.create_dataset(key, data=arr, compression="gzip" if big else None,
                             compression_opts=4 if big else None, shuffle=big)
    for name, arr in session.quality.items():
        group.create_dataset(f"quality/{name}", data=np.asarray(arr))


def read_processed(path: str | os.PathLike) -> ProcessedSession:
    """Read and validate a processed-session file.

    Raises:
        SchemaError: the file is missing, not HDF5, truncated, from a newer schema, or lacks a
            key / has a wrong shape or dtype; the message names the file and the key.
    """
    path = Path(path)
    if not path.is_file():
        raise SchemaError(f"{path}: no such file")
    try:
        h5 = h5py.File(path, "r")
    except OSError as e:
        raise SchemaError(f"{path}: not a readable HDF5 file (truncated or corrupted?): {e}") from e
    with h5:
        return read_session_group(h5, str(path))


def read_session_group(group: h5py.Group, where: str | None = None) -> ProcessedSession:
    """Read and validate a session written by :func:`write_session_group` (a whole processed
    file or one group of an augmented dataset); errors name ``where`` (default: file:group)."""
    where = where or f"{group.file.filename}:{group.name}"
    attrs = dict(group.attrs)
    missing_attrs = [a for a in ("schema_version", "session", "fps") if a not in attrs]
    if missing_attrs:
        raise SchemaError(f"{where}: missing file attributes {missing_attrs}; not a couch "
                          "processed session")
    version = int(attrs["schema_version"])
    if version > SCHEMA_VERSION:
        raise SchemaError(f"{where}: schema_version {version} is newer than this couch "
                          f"({__version__}) reads ({SCHEMA_VERSION}); upgrade couch")
    keys = {f.path: f.path.lstrip("/") for f in FIELDS}
    missing = [f.path for f in FIELDS if keys[f.path] not in group]
    if missing:
        raise SchemaError(f"{where}: missing keys {missing}")
    values: dict[str, Any] = {}
    for f in FIELDS:
        try:
            data = group[keys[f.path]][()]
        except (OSError, KeyError, ValueError) as e:
            raise SchemaError(f"{where}: cannot read '{f.path}' ({e})") from e
        if f.dtype == "str":
            data = data.decode() if isinstance(data, bytes) else tuple(
                d.decode() if isinstance(d, bytes) else str(d) for d in data)
        values[f.attr] = data
    quality = ({k: group["quality"][k][()] for k in group["quality"]}
               if "quality" in group else {})
    session = ProcessedSession(
        session=str(attrs["session"]), fps=float(attrs["fps"]), quality=quality,
        couch_version=str(attrs.get("couch_version", "unknown")), schema_version=version,
        **values)
    validate(session, where)
    return session
