"""Which files make up a recorded session folder: the one reader of ``session.json``.

A session folder (``couch-simulate``'s layout, and what a capture rig writes) holds
``kinect/<serial>.mkv``, ``calibration/<serial>.mkv`` (ChArUco captures),
``background/<serial>.mkv`` (the empty room, optional), ``imu/*.mvnx``, optionally a scan of the
subject (``subject/scan.ply`` or ``.obj``, a mesh in metres) and a ``session.json`` manifest
naming them::

    {"kinect": [{"serial": "...", "file": "kinect/<serial>.mkv", "sync": "MASTER",
                 "calibration_capture": "calibration/<serial>.mkv",
                 "background": "background/<serial>.mkv" | null}, ...],
     "imu": {"mvnx": "imu/recording.mvnx", ...}, "board": {...ChArUco BoardSpec fields...},
     "subject": {"scan": "subject/scan.ply"}, "chair_scan": "chair_scan.obj"}

Without a manifest the folders are listed instead (cameras by file stem, in name order).
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["CameraFiles", "SessionFiles", "SessionLayoutError", "session_files"]


class SessionLayoutError(ValueError):
    """``session.json`` is malformed (the message names the manifest)."""


@dataclass(frozen=True)
class CameraFiles:
    """One Kinect's files in a session.

    Attributes:
        serial: device serial.
        recording: the session recording (``kinect/<serial>.mkv``), or None.
        calibration_capture: its ChArUco board capture, or None.
        background: its empty-room recording, or None (none, or the manifest says null).
        sync: ``MASTER`` / ``SUBORDINATE`` / ``""`` (unknown).
    """

    serial: str
    recording: Path | None
    calibration_capture: Path | None
    background: Path | None
    sync: str = ""


@dataclass(frozen=True)
class SessionFiles:
    """A session folder's files.

    Attributes:
        root: the folder.
        manifest: its ``session.json``, or None when the folders were listed instead.
        cameras: the Kinects in the manifest's order (or by serial).
        mvnx: the IMU's MVNX export, or None.
        board: the manifest's ChArUco board fields, or None.
        subject_scan: a mesh of the subject (for the body shape), or None.
        chair_scan: the object's scan mesh: the manifest's ``chair_scan``, else
            ``chair_scan.obj`` / ``.ply`` when present, else None.
    """

    root: Path
    manifest: Path | None
    cameras: list[CameraFiles]
    mvnx: Path | None
    board: dict[str, Any] | None
    subject_scan: Path | None = None
    chair_scan: Path | None = None

    def camera(self, serial: str) -> CameraFiles | None:
        """The camera ``serial``, or None if the session has no such camera."""
        return next((c for c in self.cameras if c.serial == str(serial)), None)


def session_files(session_dir: str | os.PathLike) -> SessionFiles:
    """The files of a session folder, from ``session.json`` when it has one.

    Files the manifest names are returned as named, whether or not they exist (the step that
    reads one reports it missing); ``background/<serial>.mkv`` and ``imu/*.mvnx`` stand in,
    when present, where the manifest is silent. Without a manifest: ``kinect/*.mkv`` and
    ``calibration/*.mkv`` by stem, ``background/<serial>.mkv`` when present, the first
    ``imu/*.mvnx``.

    Raises:
        SessionLayoutError: malformed JSON, no ``kinect`` list, or an entry without ``serial``.
    """
    root = Path(session_dir)
    manifest = root / "session.json"
    if not manifest.is_file():
        return _listed(root)
    try:
        doc = json.loads(manifest.read_text())
        cameras = []
        for k in doc["kinect"]:
            serial = str(k["serial"])
            if "background" in k:
                background = None if k["background"] is None else root / k["background"]
            else:
                default = root / "background" / f"{serial}.mkv"
                background = default if default.is_file() else None
            cal = k.get("calibration_capture")
            cameras.append(CameraFiles(serial, root / k["file"] if k.get("file") else None,
                                       root / cal if cal else None, background,
                                       str(k.get("sync", ""))))
        mvnx_entry = (doc.get("imu") or {}).get("mvnx")
        board = doc.get("board")
        scan_entry = (doc.get("subject") or {}).get("scan")
        chair_entry = doc.get("chair_scan")
    except (json.JSONDecodeError, KeyError, TypeError, AttributeError) as exc:
        raise SessionLayoutError(f"{manifest}: malformed session manifest ({exc!r})") from None
    mvnx = root / mvnx_entry if mvnx_entry else _first(root / "imu", "*.mvnx")
    scan = root / scan_entry if scan_entry else _subject_scan(root)
    chair = root / chair_entry if chair_entry else _chair_scan(root)
    return SessionFiles(root, manifest, cameras, mvnx, board if isinstance(board, dict) else None,
                        scan, chair)


def _first(folder: Path, pattern: str) -> Path | None:
    found = sorted(folder.glob(pattern))
    return found[0] if found else None


def _listed(root: Path) -> SessionFiles:
    recordings = {p.stem: p for p in sorted((root / "kinect").glob("*.mkv"))}
    captures = {p.stem: p for p in sorted((root / "calibration").glob("*.mkv"))}
    cameras = []
    for serial in sorted(recordings.keys() | captures.keys()):
        bg = root / "background" / f"{serial}.mkv"
        cameras.append(CameraFiles(serial, recordings.get(serial), captures.get(serial),
                                   bg if bg.is_file() else None))
    return SessionFiles(root, None, cameras, _first(root / "imu", "*.mvnx"), None,
                        _subject_scan(root), _chair_scan(root))


def _chair_scan(root: Path) -> Path | None:
    return next((p for p in (root / "chair_scan.obj", root / "chair_scan.ply") if p.is_file()),
                None)


def _subject_scan(root: Path) -> Path | None:
    return next((p for p in (root / "subject" / "scan.ply", root / "subject" / "scan.obj")
                 if p.is_file()), None)
