"""Software 2x2 binning of full-resolution depth (:mod:`couch.capture.binning`)."""

from __future__ import annotations

import numpy as np
import pytest

from couch.capture.binning import bin_depth, bin_ir


def test_a_block_is_the_mean_of_its_valid_pixels_when_they_agree():
    depth = np.array([[2000, 2004, 1000, 3000, 0, 0],
                      [2002, 2006, 1000, 3000, 0, 1500]], np.uint16)
    out = bin_depth(depth)
    assert out.shape == (1, 3) and out.dtype == np.uint16
    # one surface: the mean; an edge between two (1 m and 3 m): invalid, not a depth between;
    # a single valid pixel: invalid
    assert out.tolist() == [[2003, 0, 0]]


def test_two_agreeing_pixels_make_a_block_and_the_tolerance_grows_with_depth():
    near = np.array([[1000, 0], [0, 1010]], np.uint16)  # 10 mm apart at 1 m: within 2 % + 5 mm
    far = np.array([[4000, 4090], [0, 0]], np.uint16)  # 90 mm apart at 4 m: within 85 mm? no
    assert bin_depth(near).item() == 1005
    assert bin_depth(far).item() == 0
    assert bin_depth(far, tolerance=0.03).item() == 4045
    assert bin_depth(near, min_valid=3).item() == 0


def test_ir_is_the_block_mean_and_odd_sizes_are_refused():
    ir = np.array([[10, 20, 7, 7], [30, 40, 7, 8]], np.uint16)
    assert bin_ir(ir).tolist() == [[25, 7]]
    with pytest.raises(ValueError, match="even image size"):
        bin_depth(np.zeros((3, 4), np.uint16))
