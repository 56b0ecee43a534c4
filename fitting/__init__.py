"""Fitting stage: body fits to point clouds, chair registration, contacts, `couch-process`.

Built so far: :mod:`couch.fitting.metrics` (MPJPE, chamfer, foot skate, jitter, sync error)."""

from couch.fitting.metrics import (
    FOOT_KEYPOINTS,
    SurfaceDistances,
    chamfer,
    foot_points,
    foot_skate,
    jitter,
    mpjpe,
    surface_distances,
    sync_error,
)

__all__ = [
    "FOOT_KEYPOINTS", "SurfaceDistances", "chamfer", "foot_points", "foot_skate", "jitter",
    "mpjpe", "surface_distances", "sync_error",
]
