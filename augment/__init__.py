"""Augmentation stage: chair swaps, contact transfer and IK re-posing, `couch-augment`.

Public API so far:

- :class:`ShapeEntry`, :class:`ShapeLibrary`, :func:`load_shape_library` (``shapes.py``): a
  library of chair and sofa meshes read from ShapeNetCore v2 (chair 03001627, sofa 04256520) or
  any folder of OBJ/PLY files, repaired to watertight meshes (pymeshlab, alpha wrap when
  needed), put into the chair frame (metres, +Y up, floor y = 0, seat centred on x = z = 0,
  front +Z) at a plausible seat height, classified as straight / armchair / sofa, and cached.

- :func:`segment_parts`, :class:`ChairParts`, :class:`PartFrame`, :data:`PART_NAMES`
  (``parts.py``): per-face seat / backrest / left and right armrest / other labels of a
  chair-frame mesh from its geometry, with a box frame per part for part-relative coordinates.
- :func:`transfer_contacts`, :class:`TransferResult` (``transfer.py``): part-aware transfer of
  contact points from one chair's surface to another's (same part, same normalised position,
  projected onto that part; nearest-surface fallback flagged per point).

Object switch/scale and IK re-posing follow in the augmentation issue.
"""

from couch.augment.parts import PART_NAMES, ChairParts, PartFrame, segment_parts
from couch.augment.shapes import ShapeEntry, ShapeLibrary, load_shape_library
from couch.augment.transfer import TransferResult, transfer_contacts

__all__ = [
    "PART_NAMES",
    "ChairParts",
    "PartFrame",
    "ShapeEntry",
    "ShapeLibrary",
    "TransferResult",
    "load_shape_library",
    "segment_parts",
    "transfer_contacts",
]
