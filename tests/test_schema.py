"""Processed-session HDF5: round trip, validation, atomic writes, and couch-inspect."""

from __future__ import annotations

import dataclasses
import subprocess
import sys

import h5py
import numpy as np
import pytest

from couch.cli import inspect_main
from couch.schema import (
    FIELDS,
    SCHEMA_VERSION,
    SchemaError,
    read_processed,
    validate,
    write_processed,
)


def test_round_trip_keeps_every_field(tmp_path, processed_session):
    path = tmp_path / "processed.h5"
    write_processed(path, processed_session)
    back = read_processed(path)
    for f in FIELDS:
        a, b = getattr(processed_session, f.attr), getattr(back, f.attr)
        if f.dtype == "str":
            assert tuple(np.atleast_1d(a)) == tuple(np.atleast_1d(b))
        else:
            assert np.asarray(b).dtype == np.dtype(f.dtype), f.path
            np.testing.assert_array_equal(np.asarray(a, dtype=f.dtype), b, err_msg=f.path)
    assert back.session == "test_session" and back.fps == 30.0
    assert back.schema_version == SCHEMA_VERSION
    np.testing.assert_array_equal(back.quality["fit_error_mm"], np.ones(40))
    with h5py.File(path) as h5:  # an independent look at the layout DESIGN.md promises
        assert h5.attrs["schema_version"] == SCHEMA_VERSION
        assert h5["/smpl/body_pose"].shape == (40, 69)
        assert h5["/joints"].compression == "gzip"
        assert [n.decode() for n in h5["/contacts/names"][()]] == [
            "pelvis", "left_hand", "right_hand", "left_foot", "right_foot"]


@pytest.mark.parametrize("change,message", [
    ({"body_pose": np.zeros((40, 68), np.float32)}, r"'/smpl/body_pose' has shape \(40, 68\)"),
    ({"joints": np.zeros((39, 24, 3), np.float32)}, r"'/joints' has shape \(39, 24, 3\), "
                                                    r"expected \(T=40, 24, 3\)"),
    ({"contact_active": np.zeros((40, 5), np.float32)}, r"'/contacts/active' has dtype float32"),
    ({"time": np.zeros(40)}, r"'/time' does not increase at frame 1"),
    ({"interaction": np.full(40, 9, np.int8)}, r"outside 0..5"),
    ({"contact_names": ("a", "b", "c", "d", "e")}, r"'/contacts/names' is"),
])
def test_invalid_sessions_are_refused_before_writing(tmp_path, processed_session, change,
                                                     message):
    bad = dataclasses.replace(processed_session, **change)
    with pytest.raises(SchemaError, match=message):
        validate(bad)
    with pytest.raises(SchemaError, match=r"processed\.h5"):
        write_processed(tmp_path / "processed.h5", bad)
    assert not (tmp_path / "processed.h5").exists()
    assert list(tmp_path.iterdir()) == []  # no temp file left behind


def test_failed_write_leaves_the_old_file(tmp_path, processed_session, monkeypatch):
    path = tmp_path / "processed.h5"
    write_processed(path, processed_session)
    before = path.read_bytes()
    broken = dataclasses.replace(processed_session, quality={"bad": np.array([object()])})
    with pytest.raises(SchemaError):
        write_processed(path, broken)

    def explode(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(h5py.Group, "create_dataset", explode)
    with pytest.raises(KeyboardInterrupt):
        write_processed(path, processed_session)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["processed.h5"]


def test_truncated_file_gives_a_clear_error(tmp_path, processed_session):
    path = tmp_path / "processed.h5"
    write_processed(path, processed_session)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(SchemaError, match=r"processed\.h5.*not a readable HDF5|cannot read"):
        read_processed(path)
    path.write_bytes(b"not hdf5 at all")
    with pytest.raises(SchemaError, match="not a readable HDF5 file"):
        read_processed(path)
    with pytest.raises(SchemaError, match="no such file"):
        read_processed(tmp_path / "absent.h5")


def test_missing_key_wrong_shape_and_newer_version(tmp_path, processed_session):
    path = tmp_path / "processed.h5"
    write_processed(path, processed_session)
    with h5py.File(path, "a") as h5:
        del h5["/contacts/points"]
    with pytest.raises(SchemaError, match=r"missing keys \['/contacts/points'\]"):
        read_processed(path)
    write_processed(path, processed_session)
    with h5py.File(path, "a") as h5:
        del h5["/smpl/transl"]
        h5["/smpl/transl"] = np.zeros((40, 2), np.float32)
    with pytest.raises(SchemaError, match=r"'/smpl/transl' has shape \(40, 2\)"):
        read_processed(path)
    write_processed(path, processed_session)
    with h5py.File(path, "a") as h5:
        h5.attrs["schema_version"] = SCHEMA_VERSION + 1
    with pytest.raises(SchemaError, match="newer than this couch"):
        read_processed(path)
    with h5py.File(tmp_path / "other.h5", "w") as h5:
        h5["x"] = 1
    with pytest.raises(SchemaError, match="not a couch processed session"):
        read_processed(tmp_path / "other.h5")


def test_couch_inspect_summarises_and_fails_cleanly(tmp_path, processed_session, capsys):
    path = tmp_path / "processed.h5"
    write_processed(path, processed_session)
    assert inspect_main([str(path)]) == 0
    out = capsys.readouterr().out
    assert "40 at 30 fps, 1.30 s" in out
    assert "pelvis" in out and "15   37.5%" in out  # 15 of 40 frames seated
    assert "left_foot" in out and "40  100.0%" in out
    assert "box_chair: 8 vertices, 2 faces" in out
    assert "4 no hand contact" in out
    (tmp_path / "bad.h5").write_bytes(b"garbage")
    assert inspect_main([str(tmp_path / "bad.h5")]) == 1
    assert "bad.h5" in capsys.readouterr().err


def test_couch_inspect_console_script_exit_code(tmp_path):
    (tmp_path / "bad.h5").write_bytes(b"garbage")
    exe = [sys.executable, "-m", "couch.cli", str(tmp_path / "bad.h5")]
    result = subprocess.run(exe, capture_output=True, text=True, check=False)
    assert result.returncode == 1 and "invalid file" in result.stderr


def test_atomic_write_gives_ordinary_permissions(tmp_path, processed_session):
    import os

    path = tmp_path / "processed.h5"
    write_processed(path, processed_session)
    umask = os.umask(0)
    os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~umask


def test_cli_parse_args_returns_argparse_exit_codes(capsys):
    """A ``main`` returns argparse's exit code instead of raising: 0 after --help, 2 after a
    usage error (whose message argparse printed), the namespace otherwise."""
    import argparse

    from couch.cli import parse_args

    p = argparse.ArgumentParser(prog="x")
    p.add_argument("--n", type=int)
    assert parse_args(p, ["--help"]) == 0
    assert parse_args(p, ["--n", "a"]) == 2
    assert "invalid int value" in capsys.readouterr().err
    assert parse_args(p, ["--n", "3"]).n == 3
