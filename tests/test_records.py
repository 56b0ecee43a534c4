"""couch.records: dataclasses to and from HDF5 (the pipeline's stage cache)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import h5py
import numpy as np
import pytest

from couch.records import RecordError, read_record, write_record


@dataclasses.dataclass
class Part:
    name: str
    pose: np.ndarray
    score: float = np.nan


@dataclasses.dataclass
class Whole:
    path: Path | None
    values: np.ndarray
    flags: np.ndarray
    parts: list[Part]
    main: Part
    pairs: list[tuple[int, str]]
    names: tuple[str, ...]
    seconds: dict[str, float]
    ratio: float
    note: str = "default"


@dataclasses.dataclass
class Other:
    x: int


def _whole() -> Whole:
    rng = np.random.default_rng(0)
    return Whole(path=Path("/data/s1/chair.obj"), values=rng.normal(size=(50, 4, 4)),
                 flags=rng.random((7, 5)) > 0.5,
                 parts=[Part("a", np.eye(4)), Part("b", 2 * np.eye(4), 0.25)],
                 main=Part("m", np.zeros(3), float("inf")), pairs=[(3, "occluded"), (9, "far")],
                 names=("pelvis", "left_hand"), seconds={"icp": 1.5, "global": 10.0},
                 ratio=float("nan"))


def test_round_trip(tmp_path):
    w = _whole()
    write_record(tmp_path / "w.h5", w)
    back = read_record(tmp_path / "w.h5", Whole)
    assert back.path == w.path and isinstance(back.path, Path)
    assert np.array_equal(back.values, w.values) and back.values.dtype == np.float64
    assert np.array_equal(back.flags, w.flags) and back.flags.dtype == np.bool_
    assert [p.name for p in back.parts] == ["a", "b"] and back.parts[1].score == 0.25
    assert np.isnan(back.parts[0].score) and back.main.score == np.inf
    assert np.array_equal(back.parts[1].pose, 2 * np.eye(4))
    assert back.pairs == [(3, "occluded"), (9, "far")] and back.names == w.names
    assert back.seconds == w.seconds and np.isnan(back.ratio) and back.note == "default"
    with h5py.File(tmp_path / "w.h5") as h5:  # plain HDF5: arrays are datasets
        assert h5["values"].shape == (50, 4, 4)


def test_wrong_class_missing_field_and_bad_file(tmp_path):
    write_record(tmp_path / "w.h5", _whole())
    with pytest.raises(RecordError, match="holds a Whole, not a Other"):
        read_record(tmp_path / "w.h5", Other)
    with h5py.File(tmp_path / "w.h5", "a") as h5:
        del h5["values"]
    with pytest.raises(RecordError, match="field 'values' of Whole is missing"):
        read_record(tmp_path / "w.h5", Whole)
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    with pytest.raises(RecordError, match=r"bad\.h5"):
        read_record(tmp_path / "bad.h5", Whole)
    with pytest.raises(RecordError, match=r"missing\.h5"):
        read_record(tmp_path / "missing.h5", Whole)


def test_object_arrays_are_refused(tmp_path):
    w = _whole()
    w.values = np.array([None, 1], dtype=object)
    with pytest.raises(TypeError, match="object arrays"):
        write_record(tmp_path / "w.h5", w)
    assert not (tmp_path / "w.h5").exists()  # nothing half-written
