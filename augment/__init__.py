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
  projected onto that part; nearest-surface fallback flagged per point), or in metres relative
  to the sitter's place on the new chair (:func:`sitter_shift`); :func:`contact_parts`.
- :class:`SignedDistanceGrid` (``sdf.py``): a chair's signed distance on a grid, queried in
  numpy or differentiably in torch (the IK's penetration term, occupancy for synthesis).

- :func:`smooth_offsets`, :func:`contact_targets`, :func:`reference_vertices`,
  :func:`default_reference`, :func:`reposition`, :class:`IKConfig`, :class:`IKResult`,
  :func:`penetration`, :data:`DISTAL_JOINTS` (``ik.py``): TRUMANS-style offset smoothing
  (linear falloff over a window, norm-weighted blending) and batched full-body IK over all
  frames (reach, keep the captured pose, planted feet, temporal smoothness, joint limits,
  clipped steps with larger bounds for distal bones); deepest body-into-chair penetration.

- :func:`canonical_chair_frame`, :func:`augment_sequence`, :func:`augment_dataset`,
  :func:`find_processed`, :class:`AugmentResult`, :class:`AugmentStats`,
  :class:`AugmentSummary` (``dataset.py``): object switch/scale at the source chair's frame,
  contact transfer, IK and penetration checks per sequence, and the augmented dataset
  (``augmented.h5`` + ``summary.json``) over a local process pool; ``couch-augment``
  (``cli.py``).
"""

from couch.augment.dataset import (
    AugmentResult,
    AugmentStats,
    AugmentSummary,
    augment_dataset,
    augment_sequence,
    canonical_chair_frame,
    find_processed,
)
from couch.augment.ik import (
    DISTAL_JOINTS,
    IKConfig,
    IKResult,
    contact_targets,
    default_reference,
    penetration,
    reference_vertices,
    reposition,
    smooth_offsets,
)
from couch.augment.parts import PART_NAMES, ChairParts, PartFrame, segment_parts
from couch.augment.sdf import SignedDistanceGrid
from couch.augment.shapes import ShapeEntry, ShapeLibrary, load_shape_library
from couch.augment.transfer import TransferResult, contact_parts, sitter_shift, transfer_contacts

__all__ = [
    "DISTAL_JOINTS",
    "PART_NAMES",
    "AugmentResult",
    "AugmentStats",
    "AugmentSummary",
    "ChairParts",
    "IKConfig",
    "IKResult",
    "PartFrame",
    "ShapeEntry",
    "ShapeLibrary",
    "SignedDistanceGrid",
    "TransferResult",
    "augment_dataset",
    "augment_sequence",
    "canonical_chair_frame",
    "contact_parts",
    "contact_targets",
    "default_reference",
    "find_processed",
    "load_shape_library",
    "penetration",
    "reference_vertices",
    "reposition",
    "segment_parts",
    "sitter_shift",
    "smooth_offsets",
    "transfer_contacts",
]
