"""Synthesis stage: COUCH's ControlNet, PoseNet and ContactNet, their features and training.

Public API so far (the runtime controller, ``couch-synthesize``, the baseline harness and
``couch-eval`` are still to come):

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
"""

from couch.synthesis.data import FeatureCache, SequenceRef, build_cache, find_sequences, split
from couch.synthesis.features import (
    LAYOUT,
    FeatureConfig,
    FeatureStats,
    SequenceFeatures,
    sequence_features,
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
from couch.synthesis.train import TrainConfig, TrainResult, load_trained, train

__all__ = [
    "LAYOUT",
    "ContactNet",
    "ContactNetConfig",
    "ControlNet",
    "ControlNetConfig",
    "FeatureCache",
    "FeatureConfig",
    "FeatureStats",
    "PoseNet",
    "PoseNetConfig",
    "SequenceFeatures",
    "SequenceRef",
    "TrainConfig",
    "TrainResult",
    "build_cache",
    "control_loss",
    "find_sequences",
    "load_trained",
    "project_contacts",
    "rollout",
    "sequence_features",
    "split",
    "train",
]
