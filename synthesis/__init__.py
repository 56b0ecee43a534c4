"""Synthesis stage: COUCH's ControlNet, PoseNet and ContactNet, their features and training.

Public API, by module:

- ``features.py``: :class:`FeatureConfig` (the paper's numbers), :func:`sequence_features`
  (J, T, G, I, E, hand local phases, global phase, control signals and every network target of
  one processed sequence, resampled to 30 fps), :class:`SequenceFeatures`, :data:`LAYOUT`
  (which groups each network reads and predicts), :class:`FeatureStats` (normalisation, npz).
- ``nets.py``: :class:`ControlNet`, :class:`PoseNet` (mixture of experts), :class:`ContactNet`
  (cVAE), their ``*Config`` dataclasses (``released_code()`` variants), :func:`rollout`
  (scheduled sampling), :func:`control_loss`, :func:`project_contacts`.
- ``data.py``: :func:`find_sequences`, :func:`build_cache` (``features.h5``, reused while the
  sources are unchanged), :class:`FeatureCache`, :func:`split` (held-out chairs).
- ``train.py``: :func:`train` and ``couch-train`` (presets ``paper`` and ``ci``, checkpoints,
  resume, ``log.csv`` + ``curves.png``), :func:`load_trained`.
- ``controller.py``: :class:`Synthesizer` (the runtime controller: PoseNet alone on the
  approach, ControlNet switched on near each contact, series of contacts, batched characters;
  ``method="baseline"`` runs NSM+Control in the same loop, ``method="nsm"`` the plain NSM),
  :class:`Scene`,
  :class:`SynthesisResult`, :func:`yaw_transform`.
- ``plans.py``: :func:`replay_plans` (a trained ControlNet run over a feature cache as the
  runtime runs it: PoseNet's control input for ``TrainConfig.control_source="controlnet"``),
  :func:`control_step` (one batched ControlNet frame, the controller's), :func:`replan_lost`.
- ``sampling.py``: :func:`sample_contacts` (ContactNet samples projected onto the chair).
- ``foot_lock.py``: :func:`lock_feet` (planted feet held by leg IK after synthesis;
  ``Synthesizer(foot_lock=True)``), :class:`FootLockConfig`, :func:`planted_feet`.
- ``export.py``: :func:`save_npz`, :func:`to_processed`, :func:`write_processed_sessions`.
- ``precision.py``: :func:`packed_copy` (a network's large layers as fbgemm fp16 or int8 GEMMs
  for inference; ``Synthesizer(precision=...)``), :data:`PRECISIONS`.
- ``metrics.py``: ACE (and where a hand stopped, :func:`closest_hand_offsets`), AP@k, APD,
  contact APD, foot sliding, penetration, :func:`format_table`.
"""

from couch.synthesis.controller import METHODS, Scene, SynthesisResult, Synthesizer, yaw_transform
from couch.synthesis.data import FeatureCache, SequenceRef, build_cache, find_sequences, split
from couch.synthesis.export import save_npz, to_processed, write_processed_sessions
from couch.synthesis.features import (
    LAYOUT,
    FeatureConfig,
    FeatureStats,
    SequenceFeatures,
    sequence_features,
)
from couch.synthesis.foot_lock import FootLockConfig, lock_feet, planted_feet
from couch.synthesis.metrics import (
    ace,
    apd,
    closest_hand_distances,
    closest_hand_offsets,
    contact_apd,
    contact_intervals,
    contact_precision,
    foot_sliding,
    format_intervals,
    format_table,
    penetration,
    pose_feature_apd,
)
from couch.synthesis.nets import (
    ContactNet,
    ContactNetConfig,
    ControlNet,
    ControlNetConfig,
    PoseNet,
    PoseNetConfig,
    control_loss,
    project_contacts,
    rollout,
)
from couch.synthesis.plans import REPLAN_RADIUS, control_step, replan_lost, replay_plans
from couch.synthesis.precision import PRECISIONS, Precision, packed_copy
from couch.synthesis.sampling import sample_contacts
from couch.synthesis.train import (
    TrainConfig,
    TrainResult,
    Which,
    load_trained,
    parse_which,
    preset_config,
    train,
)

__all__ = [
    "LAYOUT",
    "METHODS",
    "PRECISIONS",
    "REPLAN_RADIUS",
    "ContactNet",
    "ContactNetConfig",
    "ControlNet",
    "ControlNetConfig",
    "FeatureCache",
    "FeatureConfig",
    "FeatureStats",
    "FootLockConfig",
    "PoseNet",
    "PoseNetConfig",
    "Precision",
    "Scene",
    "SequenceFeatures",
    "SequenceRef",
    "SynthesisResult",
    "Synthesizer",
    "TrainConfig",
    "TrainResult",
    "Which",
    "ace",
    "apd",
    "build_cache",
    "closest_hand_distances",
    "closest_hand_offsets",
    "contact_apd",
    "contact_intervals",
    "contact_precision",
    "control_loss",
    "control_step",
    "find_sequences",
    "foot_sliding",
    "format_intervals",
    "format_table",
    "load_trained",
    "lock_feet",
    "packed_copy",
    "parse_which",
    "penetration",
    "planted_feet",
    "pose_feature_apd",
    "preset_config",
    "project_contacts",
    "replan_lost",
    "replay_plans",
    "rollout",
    "sample_contacts",
    "save_npz",
    "sequence_features",
    "split",
    "to_processed",
    "train",
    "write_processed_sessions",
    "yaw_transform",
]
