"""`make demo`'s job: the bundled body seated on a box, written as a PNG."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d

from couch.geometry import look_at
from couch.tools.demo import main, seated_body
from couch.tools.render import Mesh, render


def test_seated_body_has_feet_on_the_floor_and_hands_on_the_thighs(body_model):
    v, seat = seated_body("couch-body")
    sets = body_model.contact_vertices
    soles = np.concatenate([sets["left_foot"], sets["right_foot"]])
    assert abs(v[soles, 1].min()) < 1e-6
    assert 0.35 < seat < 0.55  # a chair's seat height
    for side in ("left_hand", "right_hand"):
        palm = v[sets[side]]
        assert seat < palm[:, 1].min() < seat + 0.4  # above the seat, below the chest
        assert palm[:, 2].mean() > v[sets["pelvis"], 2].mean() + 0.2  # forward, over the thighs


def test_demo_writes_a_png_showing_the_body(tmp_path):
    out = tmp_path / "demo.png"
    main(["-o", str(out), "--model", "couch-body-coarse", "--size", "160"])
    image = cv2.imread(str(out))
    assert image.shape == (160, 320, 3)
    b, g, r = np.moveaxis(image.astype(int), -1, 0)
    skin = (r - b > 40) & (r > g)  # the body's warm skin tone; floor and background are grey
    assert skin[:, :160].mean() > 0.02 and skin[:, 160:].mean() > 0.02  # front and side views
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 50  # shaded, not flat


def test_render_depth_is_distance_along_the_optical_axis():
    plane = o3d.geometry.TriangleMesh.create_box(4.0, 4.0, 0.01)
    v = np.asarray(plane.vertices) - [2.0, 2.0, 0.0]
    k = np.array([[100.0, 0, 64], [0, 100.0, 48], [0, 0, 1]])
    pose = look_at([0.0, 0.0, -2.5], [0.0, 0.0, 0.0])
    res = render([Mesh(v, np.asarray(plane.triangles))], k, pose, 128, 96)
    assert np.allclose(res.depth, 2.5, atol=1e-4)  # flat: depth, not ray length
    assert (res.mesh_id == 0).all()
