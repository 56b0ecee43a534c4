"""couch.tools.motion_preview: camera framing, rendering with markers, MP4 and contact sheet."""

from __future__ import annotations

import av
import cv2
import numpy as np
import pytest
import torch
import trimesh

from couch.body import standing_pose
from couch.geometry import apply_transform, invert_transform
from couch.tools.motion_preview import (
    contact_sheet,
    framing_points,
    preview,
    preview_camera,
    render_frames,
    write_mp4,
    write_png,
)

BACKGROUND = np.array([235, 235, 240])  # couch.tools.render.render's default
T = 5


@pytest.fixture(scope="module")
def scene(coarse_model):
    """A standing coarse body walking along +X beside a box chair, feet on the floor; one contact
    target on the chair's seat (plus a NaN row) and hand points in front of the chair."""
    transl = np.zeros((T, 3), np.float32)
    transl[:, 0] = np.linspace(-0.7, -0.4, T)
    with torch.no_grad():
        out = coarse_model(body_pose=torch.as_tensor(standing_pose())[None].repeat(T, 1),
                           transl=torch.as_tensor(transl))
    body = out.vertices.numpy().astype(np.float64)
    body[..., 1] -= body[..., 1].min()
    chair = trimesh.creation.box(extents=(0.5, 0.45, 0.5))
    chair.apply_translation((0.45, 0.225, 0.0))
    contacts = np.array([[0.45, 0.45, 0.0], [np.nan, np.nan, np.nan]])
    hands = np.tile(np.array([[0.30, 0.9, 0.45], [0.60, 0.9, 0.45]]), (T, 1, 1))
    hands[2, 1] = np.nan  # one hand out of contact in frame 2
    return {"body": body, "faces": coarse_model.faces, "chair_v": np.asarray(chair.vertices),
            "chair_f": np.asarray(chair.faces), "contacts": contacts, "hands": hands}


def _project(k: np.ndarray, pose: np.ndarray, p: np.ndarray) -> tuple[int, int]:
    c = apply_transform(invert_transform(pose), np.asarray(p, dtype=np.float64)[None])[0]
    assert c[2] > 0
    u, v = (k @ c)[:2] / c[2]
    return round(u - 0.5), round(v - 0.5)  # pixel centres are at +0.5


def _window(img: np.ndarray, uv: tuple[int, int], r: int = 3) -> np.ndarray:
    u, v = uv
    return img[max(0, v - r):v + r + 1, max(0, u - r):u + r + 1].reshape(-1, 3).astype(int)


def _red(px: np.ndarray) -> np.ndarray:
    return (px[:, 0] > 80) & (px[:, 0] > 2 * px[:, 1]) & (px[:, 0] > 2 * px[:, 2])


def _blue(px: np.ndarray) -> np.ndarray:
    return (px[:, 2] > 80) & (px[:, 2] > 1.5 * px[:, 0]) & (px[:, 2] > 1.3 * px[:, 1])


@pytest.mark.parametrize("az,el,w,h", [(30.0, 20.0, 160, 120), (90.0, 60.0, 64, 128),
                                       (-45.0, -10.0, 200, 50), (0.0, 90.0, 80, 80)])
def test_preview_camera_frames_every_point(az, el, w, h):
    pts = np.random.default_rng(0).uniform([-1, 0, -0.5], [2, 1.8, 0.5], (500, 3))
    k, pose = preview_camera(pts, w, h, azimuth_deg=az, elevation_deg=el)
    cam = apply_transform(invert_transform(pose), pts)
    assert (cam[:, 2] > 0).all()
    uv = (cam @ k.T)[:, :2] / cam[:, 2:]
    assert (uv >= 0).all() and (uv[:, 0] <= w).all() and (uv[:, 1] <= h).all()
    centre = (pts.min(0) + pts.max(0)) / 2
    np.testing.assert_allclose(apply_transform(invert_transform(pose), centre[None])[0, :2], 0,
                               atol=1e-9)  # the bounding-box centre is on the optical axis
    offset = pose[:3, 3] - centre
    assert np.sign(offset[1]) == np.sign(el)  # elevation: above (or below) the target
    if abs(el) < 90:
        horiz = np.rad2deg(np.arctan2(offset[0], offset[2]))
        assert horiz == pytest.approx(az, abs=1e-6)  # azimuth around +Y from +Z
        assert pose[1, 1] < 0  # image down (camera +Y) points down in the world


def test_preview_camera_rejects_no_points():
    with pytest.raises(ValueError, match="no finite points"):
        preview_camera(np.full((3, 3), np.nan), 96, 72)


def test_render_frames_shows_body_chair_and_markers(scene):
    w, h = 160, 120
    args = (scene["body"], scene["faces"], scene["chair_v"], scene["chair_f"])
    imgs = render_frames(*args, contacts=scene["contacts"], hands=scene["hands"],
                         frames=np.array([0, T - 1]), width=w, height=h)
    assert imgs.shape == (2, h, w, 3) and imgs.dtype == np.uint8
    # the default camera frames all frames, markers included
    k, pose = preview_camera(framing_points(scene["body"], scene["chair_v"], scene["contacts"],
                                            scene["hands"]), w, h)
    again = render_frames(*args, contacts=scene["contacts"], hands=scene["hands"],
                          frames=[T - 1], width=w, height=h, camera=(k, pose))
    np.testing.assert_array_equal(again[0], imgs[1])
    # the body: its centroid's pixel is skin, not background, and it moves between frames
    for img, t in zip(imgs, (0, T - 1), strict=True):
        px = img[_project(k, pose, scene["body"][t].mean(0))[::-1]].astype(int)
        assert np.abs(px - BACKGROUND).max() > 30, px
        assert px[0] > px[2] + 20, px  # skin: red over blue
    assert np.abs(imgs[0].astype(int) - imgs[1]).max() > 50
    # the chair: brown at its front face's centre
    px = imgs[0][_project(k, pose, np.array([0.45, 0.225, 0.25]))[::-1]].astype(int)
    assert px[0] > px[1] > px[2] and px[0] - px[2] > 40, px
    # the contact marker: red pixels around its projection, none when it is not drawn
    uv = _project(k, pose, scene["contacts"][0])
    assert _red(_window(imgs[0], uv)).sum() >= 2
    plain = render_frames(*args, frames=[0], width=w, height=h, camera=(k, pose))
    assert not _red(_window(plain[0], uv)).any()
    # the hands: blue markers at their points
    for p in scene["hands"][0]:
        assert _blue(_window(imgs[0], _project(k, pose, p))).sum() >= 2


def test_render_frames_labels_and_bad_input(scene):
    args = (scene["body"], scene["faces"], scene["chair_v"], scene["chair_f"])
    plain = render_frames(*args, frames=[0], width=96, height=72)
    labelled = render_frames(*args, frames=[0], width=96, height=72, labels=["frame 0"])
    diff = np.abs(plain.astype(int) - labelled).max(-1)[0]
    assert diff[:15, :60].any() and not diff[30:].any()  # text in the top-left corner only
    with pytest.raises(ValueError, match="body vertices"):
        render_frames(np.zeros((0, 10, 3)), scene["faces"], scene["chair_v"], scene["chair_f"])
    with pytest.raises(ValueError, match="frames"):
        render_frames(*args, frames=[T])
    with pytest.raises(ValueError, match="hands"):
        render_frames(*args, hands=np.zeros((T, 3)))
    with pytest.raises(ValueError, match="labels"):
        render_frames(*args, frames=[0, 1], labels=["only one"])


def _decode(path) -> tuple[list[np.ndarray], float]:
    with av.open(str(path)) as c:
        stream = c.streams.video[0]
        rate = float(stream.average_rate)
        return [f.to_ndarray(format="rgb24") for f in c.decode(stream)], rate


def test_preview_writes_video_and_sheet(scene, tmp_path):
    w, h = 96, 72
    out = preview(scene["body"], scene["faces"], scene["chair_v"], scene["chair_f"],
                  tmp_path / "sub" / "seq", contacts=scene["contacts"], hands=scene["hands"],
                  fps=30.0, sheet_frames=4, width=w, height=h, video_stride=2, progress=False)
    assert out == {"video": tmp_path / "sub" / "seq.mp4", "sheet": tmp_path / "sub" / "seq.png"}
    assert sorted(p.name for p in (tmp_path / "sub").iterdir()) == ["seq.mp4", "seq.png"]
    frames, rate = _decode(out["video"])
    assert len(frames) == 3 and frames[0].shape == (h, w, 3)  # frames 0, 2, 4
    assert rate == pytest.approx(15.0)
    sheet = cv2.imread(str(out["sheet"]), cv2.IMREAD_UNCHANGED)
    assert sheet.shape == (h, 4 * w, 3)  # frames 0, 1, 3, 4 on one row
    # PNG is lossless: below the labels, the tiles are exactly the rendered frames
    ref = render_frames(scene["body"], scene["faces"], scene["chair_v"], scene["chair_f"],
                        contacts=scene["contacts"], hands=scene["hands"], frames=[0, 1, 3, 4],
                        width=w, height=h)
    np.testing.assert_array_equal(sheet[..., ::-1][h // 2:],
                                  contact_sheet(ref, 4)[h // 2:])
    # the video is lossy but close to the frames it encodes (below the label)
    err = np.abs(frames[2].astype(int) - ref[3])[h // 2:].mean()
    assert err < 12, err


def test_write_mp4_pads_odd_sizes(tmp_path):
    images = np.random.default_rng(1).integers(0, 255, (4, 71, 95, 3), dtype=np.uint8)
    images[:] = images[:1]  # a still image: decodes close to the input
    path = write_mp4(images, tmp_path / "odd.mp4", fps=24.0)
    frames, rate = _decode(path)
    assert len(frames) == 4 and frames[0].shape == (72, 96, 3)
    assert rate == pytest.approx(24.0)


def test_writers_reject_empty_or_misshapen_input(scene, tmp_path):
    for bad in (np.zeros((0, 72, 96, 3), np.uint8), np.zeros((72, 96, 3), np.uint8),
                np.zeros((2, 72, 96, 4), np.uint8), np.zeros((2, 72, 96, 3))):
        with pytest.raises(ValueError, match=r"bad\.mp4"):
            write_mp4(bad, tmp_path / "bad.mp4")
    with pytest.raises(ValueError, match=r"bad\.png"):
        write_png(np.zeros((0, 5, 3), np.uint8), tmp_path / "bad.png")
    with pytest.raises(ValueError, match="seq"):
        preview(np.zeros((0, 10, 3)), scene["faces"], scene["chair_v"], scene["chair_f"],
                tmp_path / "seq", progress=False)
    assert list(tmp_path.iterdir()) == []  # nothing (not even a temporary file) left behind


def test_contact_sheet_tiles_row_major_and_pads():
    images = np.stack([np.full((3, 4, 3), 10 * (i + 1), np.uint8) for i in range(5)])
    sheet = contact_sheet(images, columns=4)
    assert sheet.shape == (6, 16, 3)
    for i in range(8):
        tile = sheet[3 * (i // 4):3 * (i // 4) + 3, 4 * (i % 4):4 * (i % 4) + 4]
        assert (tile == (10 * (i + 1) if i < 5 else 255)).all()
    assert contact_sheet(images[:2], columns=1).shape == (6, 4, 3)
