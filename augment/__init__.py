"""Augmentation stage: chair swaps, contact transfer and IK re-posing, `couch-augment`.
Filled in by the augmentation issue."""
