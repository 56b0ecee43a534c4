"""Benchmark: capture ingest throughput on a simulated session, measured in one run.

Times, for every camera of a session: streaming the MKV through
:func:`couch.capture.frames.open_kinect_stream` (demux + JPEG decode), segmenting its
depth (background model + per-frame foreground), and fusing the person's world point cloud per
frame from all cameras, and prints frames/s and the multiple of real time (camera frames per
second over the recording's frame rate × cameras).
Run: ``python -m couch.tools.bench.capture [SESSION_DIR]`` (default: a fresh 4-camera, 3 s,
30 fps session with full NFOV-unbinned depth, simulated first and not timed).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from couch.capture.frames import open_kinect_stream
from couch.capture.pointcloud import fuse_clouds
from couch.capture.segmentation import segment_recording
from couch.capture.session import session_files


def bench(session: Path) -> None:
    truth = json.loads((session / "truth.json").read_text())
    poses = {c["serial"]: np.asarray(c["world_from_depth"]) for c in truth["cameras"]}
    layout = session_files(session)
    files = {c.serial: c.recording for c in layout.cameras if c.recording is not None}
    fps = open_kinect_stream(next(iter(files.values()))).fps

    start = time.perf_counter()
    frames = 0
    for path in files.values():
        for frame in open_kinect_stream(path):
            frame.color_rgb()
            frames += 1
    read_s = time.perf_counter() - start

    rooms = {c.serial: c.background for c in layout.cameras}
    start = time.perf_counter()
    segs = {s: segment_recording(p, poses[s], empty_room=rooms[s]) for s, p in files.items()}
    seg_s = time.perf_counter() - start

    start = time.perf_counter()
    n = min(len(seg.frames) for seg in segs.values())
    points = 0
    for k in range(n):
        fs = [segs[s].frames[k] for s in files]
        cloud = fuse_clouds([f.depth_mm for f in fs], [f.person_reliable for f in fs],
                            [segs[s].calibration for s in files], [poses[s] for s in files],
                            float(k) / fps)
        points += len(cloud.points)
    fuse_s = time.perf_counter() - start

    cams = len(files)
    realtime = fps * cams
    print(f"session {session.name}: {cams} cameras, {frames} camera-frames at {fps:g} fps; "
          f"background from "
          f"{'the empty-room recordings' if all(rooms.values()) else 'the session itself'}")
    for name, seconds, count in (("read (demux + JPEG decode)", read_s, frames),
                                 ("segment (depth)", seg_s, frames),
                                 ("fuse person clouds", fuse_s, n * cams)):
        rate = count / seconds
        print(f"  {name:<28}{rate:8.1f} camera-frames/s = {rate / realtime:5.2f}x real time")
    total = read_s + seg_s + fuse_s
    print(f"  {'all three':<28}{frames / total:8.1f} camera-frames/s = "
          f"{frames / total / realtime:5.2f}x real time ({points / max(n, 1):.0f} points/frame)")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("session", nargs="?", type=Path, default=None)
    args = ap.parse_args(argv)
    if args.session is not None:
        bench(args.session)
        return
    from couch.tools.sim.session import SessionConfig, simulate_session

    with tempfile.TemporaryDirectory() as tmp:
        simulate_session(Path(tmp), SessionConfig(duration=3.0, cameras=4, charuco_poses=4,
                                                  seed=1), progress=False)
        bench(Path(tmp))


if __name__ == "__main__":
    main()
