"""Fitting stage: body fits to point clouds, chair registration, contacts, `couch-process`.

Built so far: :mod:`couch.fitting.pipeline` (:func:`run_pipeline`, the stages behind
``couch-process``: calibrate, chair, body, contacts, cached), :mod:`couch.fitting.session`
(:func:`fit_session`: sync, clouds, IMU alignment, shape, per-frame fits and fusion of a
whole session folder), :mod:`couch.fitting.chair`
(:func:`register_session_chair`: the chair scan placed in the world, moved chairs found),
:mod:`couch.fitting.contacts` (:func:`detect_contacts`: contact flags, points and interaction
labels of a motion with the chair; hand contacts still below the issue's F1),
:mod:`couch.fitting.metrics` (MPJPE, chamfer, foot skate, jitter, sync error),
:mod:`couch.fitting.body` (per-frame SMPL fits to person clouds, batched over frames),
:mod:`couch.fitting.shape` (the subject's betas from the session's clouds or a scan),
:mod:`couch.fitting.fusion` (Kinect fits + IMU over the sequence, COUCH Eq. 7-8), and their
parts: :mod:`~couch.fitting.params`, :mod:`~couch.fitting.clouds`, :mod:`~couch.fitting.nearest`,
:mod:`~couch.fitting.skinning`, :mod:`~couch.fitting.terms`, :mod:`~couch.fitting.limits`."""

from couch.fitting.body import (
    BodyFit,
    BodyFitConfig,
    cached_model,
    fit_bodies,
    fit_bodies_frame_by_frame,
)
from couch.fitting.chair import (
    ChairConfig,
    ChairRegistration,
    ChairRegistrationError,
    load_scan,
    register_chair,
    register_session_chair,
)
from couch.fitting.clouds import PaddedClouds, pad_clouds
from couch.fitting.contacts import FEET, ContactConfig, Contacts, detect_contacts
from couch.fitting.fusion import FusionConfig, contact_runs, fuse_motion
from couch.fitting.limits import joint_limit_excess, joint_limit_penalty
from couch.fitting.metrics import (
    FOOT_KEYPOINTS,
    CameraView,
    SurfaceDistances,
    chamfer,
    foot_points,
    foot_skate,
    jitter,
    mpjpe,
    surface_distances,
    sync_error,
)
from couch.fitting.params import BodyParams
from couch.fitting.pipeline import (
    STAGES,
    BodyResult,
    CalibrationResult,
    PipelineResult,
    ProcessConfig,
    ProcessError,
    StageRun,
    run_pipeline,
)
from couch.fitting.session import (
    SessionFit,
    SessionFitConfig,
    SessionFitError,
    WorldAlignment,
    fit_session,
    pose_body,
)
from couch.fitting.shape import ShapeFit, ShapeFitConfig, fit_betas_to_scan, fit_shape

__all__ = [
    "FEET",
    "FOOT_KEYPOINTS",
    "STAGES",
    "BodyFit",
    "BodyFitConfig",
    "BodyParams",
    "BodyResult",
    "CalibrationResult",
    "CameraView",
    "ChairConfig",
    "ChairRegistration",
    "ChairRegistrationError",
    "ContactConfig",
    "Contacts",
    "FusionConfig",
    "PaddedClouds",
    "PipelineResult",
    "ProcessConfig",
    "ProcessError",
    "SessionFit",
    "SessionFitConfig",
    "SessionFitError",
    "ShapeFit",
    "ShapeFitConfig",
    "StageRun",
    "SurfaceDistances",
    "WorldAlignment",
    "cached_model",
    "chamfer",
    "contact_runs",
    "detect_contacts",
    "fit_betas_to_scan",
    "fit_bodies",
    "fit_bodies_frame_by_frame",
    "fit_session",
    "fit_shape",
    "foot_points",
    "foot_skate",
    "fuse_motion",
    "jitter",
    "joint_limit_excess",
    "joint_limit_penalty",
    "load_scan",
    "mpjpe",
    "pad_clouds",
    "pose_body",
    "register_chair",
    "register_session_chair",
    "run_pipeline",
    "surface_distances",
    "sync_error",
]
