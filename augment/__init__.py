"""Augmentation stage: chair swaps, contact transfer and IK re-posing, `couch-augment`.

Public API so far:

- :class:`ShapeEntry`, :class:`ShapeLibrary`, :func:`load_shape_library` (``shapes.py``): a
  library of chair and sofa meshes read from ShapeNetCore v2 (chair 03001627, sofa 04256520) or
  any folder of OBJ/PLY files, repaired to watertight meshes (pymeshlab, alpha wrap when
  needed), put into the chair frame (metres, +Y up, floor y = 0, seat centred on x = z = 0,
  front +Z) at a plausible seat height, classified as straight / armchair / sofa, and cached.

Object switch/scale, part-aware contact transfer and IK re-posing follow in the augmentation
issue.
"""

from couch.augment.shapes import ShapeEntry, ShapeLibrary, load_shape_library

__all__ = ["ShapeEntry", "ShapeLibrary", "load_shape_library"]
