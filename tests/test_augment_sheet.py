"""The augmentation contact sheet's parts (the full sheet runs IK per shape: see README)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from couch.augment import ShapeEntry
from couch.body import CONTACT_NAMES
from couch.schema import read_processed
from couch.tools.augment_sheet import pick_frame, pick_shapes, render_tile

FIXTURE = Path(__file__).resolve().parents[1] / "fixtures" / "sessions" / "sim_fixture"


def _entry(i: str, cat: str) -> ShapeEntry:
    return ShapeEntry(id=i, source=Path(i), category=cat, vertices=np.zeros((3, 3)),
                      faces=np.zeros((1, 3), np.int64), seat_height=0.45, width=0.5, depth=0.5,
                      scale=1.0)


def test_shapes_are_taken_round_robin_over_categories():
    entries = [_entry(f"s{i}", "straight") for i in range(4)] + [_entry("a0", "armchair"),
                                                                   _entry("f0", "sofa")]
    ids = [e.id for e in pick_shapes(entries, 5)]
    assert ids == ["a0", "f0", "s0", "s1", "s2"]
    assert len(pick_shapes(entries, 20)) == 6


def test_frame_with_hand_contacts_is_chosen_and_rendered():
    s = read_processed(FIXTURE / "ground_truth.h5")
    f = pick_frame(s)
    hands = [CONTACT_NAMES.index("left_hand"), CONTACT_NAMES.index("right_hand")]
    assert s.contact_active[f, hands].sum() == s.contact_active[:, hands].sum(1).max()
    img = render_tile(s, f, "source", size=160)
    assert img.shape == (160, 160, 3) and img.dtype == np.uint8
    # body (blue-ish) and chair (orange-ish) both in view: many non-background pixels
    background = np.all(img == img[0, -1], axis=-1)
    assert (~background).mean() > 0.05
