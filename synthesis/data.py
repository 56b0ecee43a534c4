"""Training data for the synthesis networks: finding sequences, a feature cache, splits, datasets.

Pipeline (``couch-train`` drives it through :mod:`couch.synthesis.train`):

1. :func:`find_sequences` turns files and folders into :class:`SequenceRef` s (processed
   ``.h5`` files, every group of an ``augmented.h5``, simulator ``motion_*.h5`` folders).
2. :func:`build_cache` runs :func:`couch.synthesis.features.sequence_features` once per
   sequence and writes every feature group into one HDF5 ``features.h5`` (atomically). The file
   carries a hash of its sources (paths, sizes, mtimes) and of the :class:`FeatureConfig`, so a
   second call with the same inputs reuses it and changed inputs rebuild it.
3. :func:`split` holds out whole chairs (or whole sequences when there are fewer than three
   chairs) for validation; :func:`fit_stats` fits normalisation on the training rows only.
4. :class:`FrameDataset` (PoseNet, baseline, ContactNet rows) and :class:`WindowDataset`
   (ControlNet windows inside one sequence) serve batches from memory. Both implement
   ``__getitems__`` so a ``DataLoader`` slices whole batches out of numpy arrays instead of
   collating rows one by one; use them with ``collate_fn=`` :func:`collate_batch`. Built
   streamed (:meth:`FrameDataset.streamed`, ``WindowDataset(stream=True)``) they copy
   nothing and read rows from ``features.h5`` a block at a time (pieces of HDF5-chunk size
   from all over the data when shuffled), served
   by a :class:`BlockLoader` (:func:`make_loader` picks the loader).

Cache layout (``features.h5``): one dataset per feature group, (N_total, dim) float32, the rows
of all sequences one after the other (row t of a sequence = its t -> t+1 pair, see
:meth:`SequenceFeatures.as_groups`); ``/sequences/offsets`` (S+1,) int64 row offsets,
``/sequences/names`` and ``/sequences/object_names`` (S,) strings, ``/sequences/sources``
(S,) ``path`` or ``path:group``; per-sequence groups (the same value on every row, e.g. the
2048-d ContactNet condition) are stored once per sequence under ``/per_sequence/<group>``
(S, dim). Attributes: ``feature_config`` (JSON), ``source_hash``, ``format``, ``skipped``
(JSON list of [source, reason]).
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from collections.abc import Iterable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch
from tqdm import tqdm

from couch.atomic import atomic_path
from couch.schema import ProcessedSession, SchemaError, read_processed, read_session_group
from couch.synthesis.features import (
    FeatureConfig,
    FeatureStats,
    OccupancyGrid,
    canonical_chair,
    sequence_features,
    voxel_grid,
)

__all__ = [
    "CACHE_FORMAT",
    "PER_SEQUENCE_GROUPS",
    "BlockLoader",
    "FeatureCache",
    "FrameDataset",
    "SequenceRef",
    "WindowDataset",
    "build_cache",
    "chair_id",
    "chair_ids",
    "collate_batch",
    "contact_rows",
    "feature_config_from_json",
    "find_sequences",
    "fit_stats",
    "load_sequence",
    "make_loader",
    "source_hash",
    "split",
    "stack_groups",
]

#: Rows per HDF5 chunk of the cache's row groups; a streamed block is made of pieces this long
#: (:class:`BlockLoader`), so a piece is read as one chunk of each group.
CHUNK_ROWS = 256
#: Bumped whenever the cache layout or the feature code changes in a way old caches miss.
CACHE_FORMAT = 5  # 2: chairs in the canonical chair frame; 3: global_phase_update;
# 4: goal_relative_root relative to the goal root; 5: control_root_positions
#: Groups that hold the same value on every row of a sequence; stored once per sequence.
PER_SEQUENCE_GROUPS: tuple[str, ...] = ("contact_condition",)
#: File names a folder search always treats as sequences (other ``.h5`` files need the schema's
#: ``schema_version`` attribute, so caches and unrelated HDF5 files in the folder are ignored).
_KNOWN_NAMES = ("processed.h5", "augmented.h5")


# --------------------------------------------------------------------------------------------
# Finding and loading sequences
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, order=True)
class SequenceRef:
    """One sequence: an HDF5 file, and the group inside it for augmented datasets (else None)."""

    path: Path
    group: str | None = None

    def __str__(self) -> str:
        return f"{self.path}:{self.group}" if self.group is not None else str(self.path)


def _refs_in_file(path: Path, strict: bool) -> list[SequenceRef]:
    """Sequences in one HDF5 file; ``strict`` raises when the file is not in the schema (else
    returns [] so folder searches skip caches and foreign files)."""
    try:
        h5 = h5py.File(path, "r")
    except OSError as e:
        if not strict:
            return []
        raise ValueError(f"{path}: not a readable HDF5 file ({e})") from e
    with h5:
        attrs = h5.attrs
        if "schema_version" in attrs and "session" in attrs:
            return [SequenceRef(path)]
        # An augmented dataset: the root has schema_version (and kind="augmented"), each group
        # is one session written by write_session_group.
        groups = sorted(name for name, obj in h5.items()
                        if isinstance(obj, h5py.Group) and "schema_version" in obj.attrs)
        if groups:
            return [SequenceRef(path, g) for g in groups]
        if not strict:
            return []
        if "schema_version" in attrs:
            raise ValueError(f"{path}: couch file without sessions (no 'session' attribute and "
                             "no session groups)")
        raise ValueError(f"{path}: not a couch processed session or augmented dataset (no "
                         "'schema_version' attribute)")


def find_sequences(paths: Iterable[str | os.PathLike]) -> list[SequenceRef]:
    """All sequences under ``paths`` (files or folders), in a stable sorted order per path.

    Files must be processed sessions or augmented datasets (every group). Folders are searched
    recursively for ``processed.h5``, ``augmented.h5`` and ``motion_*.h5`` (each must be in the
    schema) and for other ``.h5`` files that carry the schema's ``schema_version`` attribute
    (others, e.g. a ``features.h5`` cache, are ignored). Duplicates are dropped.

    Raises:
        FileNotFoundError: a path does not exist.
        ValueError: a folder holds no sequences, or a file is not in the schema (the message
            names the path).
    """
    refs: list[SequenceRef] = []
    paths = list(paths)
    if not paths:
        raise ValueError("no data paths given")
    for raw in paths:
        path = Path(raw)
        if not path.exists():
            raise FileNotFoundError(f"{path}: no such file or folder")
        if path.is_dir():
            found: list[SequenceRef] = []
            for f in sorted(path.rglob("*.h5")):
                if f.name.startswith("."):  # atomic_path temporaries of an interrupted writer
                    continue
                known = f.name in _KNOWN_NAMES or f.name.startswith("motion_")
                found.extend(_refs_in_file(f, strict=known))
            if not found:
                raise ValueError(f"{path}: no sequences found (looked for processed.h5, "
                                 "augmented.h5, motion_*.h5 and .h5 files with a "
                                 "schema_version attribute)")
            refs.extend(found)
        else:
            refs.extend(_refs_in_file(path, strict=True))
    seen: set[tuple[str, str | None]] = set()
    unique = []
    for r in refs:
        key = (str(r.path.resolve()), r.group)
        if key not in seen:
            seen.add(key)
            unique.append(r)
    return unique


def load_sequence(ref: SequenceRef) -> ProcessedSession:
    """Read and validate one sequence (raises :class:`couch.schema.SchemaError` naming it)."""
    if ref.group is None:
        return read_processed(ref.path)
    try:
        h5 = h5py.File(ref.path, "r")
    except OSError as e:
        raise SchemaError(f"{ref.path}: not a readable HDF5 file ({e})") from e
    with h5:
        if ref.group not in h5:
            raise SchemaError(f"{ref}: no such group")
        return read_session_group(h5[ref.group], str(ref))


# --------------------------------------------------------------------------------------------
# Feature cache
# --------------------------------------------------------------------------------------------


def _config_json(config: FeatureConfig) -> str:
    return json.dumps(dataclasses.asdict(config), sort_keys=True)


def feature_config_from_json(text: str) -> FeatureConfig:
    """Inverse of the cache's ``feature_config`` attribute (lists back to tuples)."""
    values = json.loads(text)
    # runs and caches from before the setting existed: their lines end on the contact
    values.setdefault("control_line_end", 0.0)
    values.setdefault("push_off_window", None)
    return FeatureConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in values.items()})


def source_hash(refs: Sequence[SequenceRef], config: FeatureConfig) -> str:
    """sha256 over the sources (resolved path, group, size, mtime in ns), the feature config
    and :data:`CACHE_FORMAT`: any change to an input file or setting changes it."""
    h = hashlib.sha256()
    h.update(f"format={CACHE_FORMAT}\n{_config_json(config)}\n".encode())
    for r in refs:
        st = r.path.stat()
        h.update(f"{r.path.resolve()}|{r.group}|{st.st_size}|{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


class FeatureCache:
    """A ``features.h5`` opened for training; groups are read into memory on first use.

    Attributes:
        path: the cache file.
        config: the :class:`FeatureConfig` it was built with.
        offsets: (S+1,) int64 row offsets; sequence s owns rows ``offsets[s]:offsets[s+1]``.
        names, object_names, sources: (S,) per-sequence strings.
        dims: group -> width (per-row and per-sequence groups).
        skipped: [(source, reason)] sequences that feature extraction rejected.
        hit: True when :func:`build_cache` reused an existing file.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        try:
            h5 = h5py.File(self.path, "r")
        except OSError as e:
            raise ValueError(f"{self.path}: not a readable feature cache ({e})") from e
        with h5:
            if "sequences" not in h5 or "feature_config" not in h5.attrs:
                raise ValueError(f"{self.path}: not a couch feature cache (no /sequences)")
            seq = h5["sequences"]
            self.offsets = np.asarray(seq["offsets"][()], dtype=np.int64)
            self.names = [_str(x) for x in seq["names"][()]]
            self.object_names = [_str(x) for x in seq["object_names"][()]]
            self.sources = [_str(x) for x in seq["sources"][()]]
            self.config = feature_config_from_json(_str(h5.attrs["feature_config"]))
            self.source_hash = _str(h5.attrs.get("source_hash", ""))
            self.skipped = [tuple(x) for x in json.loads(_str(h5.attrs.get("skipped", "[]")))]
            self.row_groups = [k for k in h5 if isinstance(h5[k], h5py.Dataset)]
            self.sequence_groups = list(h5["per_sequence"]) if "per_sequence" in h5 else []
            self.dims = {k: int(h5[k].shape[1]) for k in self.row_groups}
            self.dims.update({k: int(h5["per_sequence"][k].shape[1])
                              for k in self.sequence_groups})
        self.hit = False
        self._data: dict[str, np.ndarray] = {}
        self._replaced: set[str] = set()
        self.row_sequence = np.repeat(np.arange(self.num_sequences), np.diff(self.offsets))

    @property
    def num_sequences(self) -> int:
        return len(self.names)

    @property
    def num_rows(self) -> int:
        return int(self.offsets[-1])

    def lengths(self) -> np.ndarray:
        """(S,) rows per sequence (frames - 1)."""
        return np.diff(self.offsets)

    def sequence_rows(self, sequences: Iterable[int]) -> np.ndarray:
        """Row indices (int64) of the given sequences, in order."""
        parts = [np.arange(self.offsets[s], self.offsets[s + 1]) for s in sequences]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.int64)

    def group(self, name: str) -> np.ndarray:
        """(N_total, dim) float32 for a per-row group, (S, dim) for a per-sequence group; read
        from disk once and kept in memory."""
        if name not in self._data:
            if name not in self.dims:
                raise KeyError(f"{self.path}: no feature group {name!r}; has {sorted(self.dims)}")
            with h5py.File(self.path, "r") as h5:
                ds = h5["per_sequence"][name] if name in self.sequence_groups else h5[name]
                self._data[name] = np.asarray(ds[()], dtype=np.float32)
        return self._data[name]

    def replace(self, name: str, values: np.ndarray) -> None:
        """Use ``values`` (N_total, dim) for the per-row group ``name`` from now on, in memory
        only (the file is untouched): e.g. PoseNet's control input as a trained ControlNet
        makes it (:func:`couch.synthesis.plans.replay_plans`)."""
        values = np.asarray(values, dtype=np.float32)
        if name not in self.row_groups or values.shape != (self.num_rows, self.dims[name]):
            raise ValueError(f"{self.path}: cannot replace {name!r} with an array of shape "
                             f"{values.shape}: expected a per-row group of shape "
                             f"({self.num_rows}, {self.dims.get(name, '?')})")
        self._data[name] = values
        self._replaced.add(name)

    def restore(self, name: str) -> None:
        """Undo :meth:`replace`: ``name`` is read from the file again on its next use."""
        self._data.pop(name, None)
        self._replaced.discard(name)

    def release(self, names: Iterable[str]) -> None:
        """Forget the in-memory copies of groups read from the file (a later use reads them
        again); groups given by :meth:`replace` are kept. PoseNet's groups are ~4,600 floats a
        row, so a cache of 300k rows holds ~5 GB once its datasets have copied them."""
        for name in names:
            if name not in self._replaced:
                self._data.pop(name, None)

    def rows(self, name: str, indices: np.ndarray) -> np.ndarray:
        """(len(indices), dim) float32 values of ``name`` at the given global rows (a
        per-sequence group is looked up through each row's sequence)."""
        data = self.group(name)
        if name in self.sequence_groups:
            return data[self.row_sequence[indices]]
        return data[indices]

    def read(self, names: Iterable[str], indices: np.ndarray) -> dict[str, np.ndarray]:
        """Like :meth:`rows` for several groups, without keeping a group in memory: a group
        already held (read or replaced) is indexed there, any other is read from the file,
        one slice per run of consecutive rows (a sequence's rows are one run). What a
        streamed dataset (:class:`BlockLoader`) and :func:`fit_stats` read through.

        Returns group -> (len(indices), dim) float32.
        """
        indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        names = list(dict.fromkeys(names))
        out = {n: self.rows(n, indices) for n in names if n in self._data}
        todo = [n for n in names if n not in out]
        for n in todo:
            if n not in self.dims:
                raise KeyError(f"{self.path}: no feature group {n!r}; has {sorted(self.dims)}")
        if not todo:
            return out
        # runs of consecutive rows: file rows [a, b) land at out[k:k + b - a]
        runs: list[tuple[int, int, int]] = []
        if len(indices):
            at = np.r_[0, np.flatnonzero(np.diff(indices) != 1) + 1]
            ends = np.r_[at[1:], len(indices)]
            runs = list(zip(indices[at].tolist(), (indices[ends - 1] + 1).tolist(), at.tolist(),
                            strict=True))
        with h5py.File(self.path, "r") as h5:
            for n in todo:
                if n in self.sequence_groups:  # (S, dim): small, read whole
                    per_seq = np.asarray(h5["per_sequence"][n][()], dtype=np.float32)
                    out[n] = per_seq[self.row_sequence[indices]]
                    continue
                x = np.empty((len(indices), self.dims[n]), dtype=np.float32)
                ds = h5[n]
                for a, b, k in runs:
                    ds.read_direct(x, np.s_[a:b], np.s_[k:k + b - a])
                out[n] = x
        return {n: out[n] for n in names}


def _str(x: Any) -> str:
    return x.decode() if isinstance(x, bytes) else str(x)


def build_cache(refs: Sequence[SequenceRef], out_path: str | os.PathLike,
                config: FeatureConfig | None = None, progress: bool = True) -> FeatureCache:
    """Compute the features of every sequence once and store them in ``out_path``.

    If ``out_path`` exists with the same :func:`source_hash` it is reused untouched (``hit``);
    otherwise it is rebuilt and replaced atomically. A sequence whose reading or feature
    extraction raises is skipped (its source and the reason are kept in ``skipped`` and
    printed); so are sequences with fewer than 2 frames (no t -> t+1 pair).

    Raises:
        ValueError: ``refs`` is empty or every sequence was skipped (with the reasons).
    """
    config = config or FeatureConfig()
    refs = list(refs)
    if not refs:
        raise ValueError(f"{out_path}: no sequences to cache")
    out_path = Path(out_path)
    key = source_hash(refs, config)
    if out_path.is_file():
        try:
            cache = FeatureCache(out_path)
        except (ValueError, KeyError, OSError):
            cache = None  # unreadable or foreign: rebuild it
        if cache is not None and cache.source_hash == key:
            cache.hit = True
            return cache

    skipped: list[tuple[str, str]] = []
    offsets = [0]
    names: list[str] = []
    objects: list[str] = []
    sources: list[str] = []
    chair_key: tuple[str, bytes] | None = None
    chair: tuple[OccupancyGrid, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None
    with atomic_path(out_path) as tmp, h5py.File(tmp, "w") as h5:
        per_seq: dict[str, list[np.ndarray]] = {}
        for ref in tqdm(refs, desc="features", unit="seq", disable=not progress):
            try:
                session = canonical_chair(load_sequence(ref))
                # Consecutive sequences on the same chair (simulator folders, augmented groups of
                # one shape) share the voxelisation and the occupancy grid, the slow part.
                ckey = (session.object_name,
                        hashlib.sha1(np.ascontiguousarray(session.object_vertices)).digest())
                if ckey != chair_key:
                    chair_key, chair = ckey, (
                        OccupancyGrid.from_mesh(session.object_vertices, session.object_faces,
                                                np.asarray(session.object_pose, np.float64),
                                                config.occupancy_voxel),
                        voxel_grid(session.object_vertices, session.object_faces,
                                   config.interaction_resolution,
                                   config.interaction_subsamples))
                assert chair is not None
                feats = sequence_features(session, config, grid=chair[0], voxels=chair[1])
                groups = feats.as_groups()
            except Exception as e:  # one bad sequence must not stop the others
                skipped.append((str(ref), f"{type(e).__name__}: {e}"))
                continue
            n = len(next(iter(groups.values())))
            if n < 1:
                skipped.append((str(ref), f"only {feats.num_frames} frame(s) at "
                                          f"{config.fps:g} fps; need 2"))
                continue
            for name, x in groups.items():
                if name in PER_SEQUENCE_GROUPS:
                    per_seq.setdefault(name, []).append(x[0])
                    continue
                if name not in h5:
                    # Resizable so sequences can be appended without holding all in memory.
                    h5.create_dataset(name, shape=(0, x.shape[1]), maxshape=(None, x.shape[1]),
                                      dtype=np.float32, chunks=(CHUNK_ROWS, x.shape[1]),
                                      compression="gzip", compression_opts=1, shuffle=True)
                ds = h5[name]
                if ds.shape[1] != x.shape[1]:
                    raise ValueError(f"{ref}: group {name} has width {x.shape[1]}, earlier "
                                     f"sequences {ds.shape[1]}")
                ds.resize(offsets[-1] + n, axis=0)
                ds[offsets[-1]:] = x
            offsets.append(offsets[-1] + n)
            names.append(session.session)
            objects.append(session.object_name)
            sources.append(str(ref))
        if not names:
            reasons = "; ".join(f"{s}: {r}" for s, r in skipped[:5])
            raise ValueError(f"all {len(refs)} sequences were skipped: {reasons}")
        ps = h5.create_group("per_sequence")
        for name, values in per_seq.items():
            ps.create_dataset(name, data=np.stack(values).astype(np.float32),
                              compression="gzip", compression_opts=1, shuffle=True)
        seq = h5.create_group("sequences")
        seq.create_dataset("offsets", data=np.asarray(offsets, dtype=np.int64))
        text = h5py.string_dtype()
        seq.create_dataset("names", data=np.array(names, dtype=object), dtype=text)
        seq.create_dataset("object_names", data=np.array(objects, dtype=object), dtype=text)
        seq.create_dataset("sources", data=np.array(sources, dtype=object), dtype=text)
        h5.attrs.update(feature_config=_config_json(config), source_hash=key,
                        format=CACHE_FORMAT, skipped=json.dumps(skipped))
    if skipped and progress:
        print(f"{out_path}: skipped {len(skipped)} of {len(refs)} sequences:")
        for s, r in skipped:
            print(f"  {s}: {r}")
    return FeatureCache(out_path)


# --------------------------------------------------------------------------------------------
# Splits and normalisation
# --------------------------------------------------------------------------------------------


def chair_id(name: str, geometry: np.ndarray) -> str:
    """A chair's identity: its name and a digest of an array that depends on its geometry
    alone (its mesh in the chair frame, or its chair-centred feature), as float32."""
    digest = hashlib.sha1(np.ascontiguousarray(geometry, np.float32).tobytes()).hexdigest()
    return f"{name}:{digest[:16]}"


def chair_ids(cache: FeatureCache) -> list[str]:
    """(S,) per-sequence chair identity: the object name and, where the cache has it, a digest
    of the chair's own feature (``contact_condition``, the chair-centred voxel grid, which
    depends on the chair's geometry alone).

    Two sequences share an id only when they share the chair: the same name and the same
    geometry. Simulated and augmented sequences name their chair by its kind ("sofa") while each
    has its own geometry; held out by name alone, a validation "chair" was a whole kind (every
    stool of 346 simulated sequences), which the networks then never trained on and which
    chose their ``best.pt``.
    """
    if "contact_condition" not in cache.sequence_groups:
        return list(cache.object_names)
    grids = cache.group("contact_condition")
    return [chair_id(name, grid) for name, grid in zip(cache.object_names, grids, strict=True)]


def split(cache: FeatureCache, val_fraction: float = 0.1, seed: int = 0,
          by: str = "object") -> tuple[np.ndarray, np.ndarray]:
    """Train / validation sequence indices (sorted int64 arrays).

    ``by="object"`` holds out whole chairs (:func:`chair_ids`: name and geometry) when there
    are at least three distinct ones, so validation measures generalisation to unseen chairs;
    otherwise (or with ``by="sequence"``) whole sequences are held out. At least one sequence
    (chair) is held out when there are two or more; a single sequence trains with an empty
    validation set.
    """
    if not 0.0 <= val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in [0, 1), got {val_fraction}")
    if by not in ("object", "sequence"):
        raise ValueError(f"split by 'object' or 'sequence', got {by!r}")
    rng = np.random.default_rng(seed)
    s = cache.num_sequences
    ids = chair_ids(cache) if by == "object" else []
    objects = sorted(set(ids))
    if by == "object" and len(objects) >= 3:
        n_val = min(len(objects) - 1, max(1, round(val_fraction * len(objects))))
        held = set(rng.permutation(objects)[:n_val].tolist()) if val_fraction > 0 else set()
        val = np.array([i for i in range(s) if ids[i] in held], dtype=np.int64)
    else:
        n_val = min(s - 1, max(1, round(val_fraction * s))) if val_fraction > 0 else 0
        val = np.sort(rng.permutation(s)[:n_val]).astype(np.int64)
    train = np.setdiff1d(np.arange(s), val).astype(np.int64)
    return train, val


def fit_stats(cache: FeatureCache, groups: Iterable[str], rows: np.ndarray,
              min_std: float | None = None, chunk: int = 16384) -> FeatureStats:
    """Per-column mean and std (floored at ``min_std``, default the cache config's) of
    ``groups`` over the given rows (the training split only, so validation stays unseen).

    Read ``chunk`` rows at a time through :meth:`FeatureCache.read` (the cache keeps no
    group it did not already hold) and combined in float64 with Chan et al.'s pairwise
    update, so memory holds one chunk, not a group in float64.
    """
    floor = cache.config.min_std if min_std is None else min_std
    rows = np.asarray(rows, dtype=np.int64)
    mean, std = {}, {}
    for name in groups:
        if len(rows) == 0:
            raise ValueError(f"{cache.path}: no rows to fit statistics of {name!r} on")
        n, mu, m2 = 0, np.zeros(cache.dims[name]), np.zeros(cache.dims[name])
        for lo in range(0, len(rows), chunk):
            x = cache.read([name], rows[lo:lo + chunk])[name].astype(np.float64)
            k, mu_k = len(x), x.mean(0)
            delta, total = mu_k - mu, n + k
            m2 += ((x - mu_k) ** 2).sum(0) + delta ** 2 * (n * k / total)
            mu += delta * (k / total)
            n = total
        mean[name] = mu.astype(np.float32)
        std[name] = np.maximum(np.sqrt(m2 / n), floor).astype(np.float32)
    return FeatureStats(mean, std)


def contact_rows(cache: FeatureCache, sequences: Iterable[int], decimals: int = 3) -> np.ndarray:
    """One row per (sequence, distinct hand-target set) with at least one hand target.

    ContactNet learns a distribution over contact sets per chair; using every frame would weight
    a set by how long the approach to it lasts (and a sequence by its length). Targets are
    compared after rounding to ``decimals`` (mm). Returns sorted global row indices.
    """
    contacts = cache.group("hand_contacts")
    mask = cache.group("hand_mask")
    out = []
    for s in sequences:
        lo, hi = int(cache.offsets[s]), int(cache.offsets[s + 1])
        seen: set[bytes] = set()
        for r in range(lo, hi):
            if not mask[r].any():
                continue
            key = np.concatenate([np.round(contacts[r], decimals), mask[r]]).tobytes()
            if key not in seen:
                seen.add(key)
                out.append(r)
    return np.asarray(out, dtype=np.int64)


# --------------------------------------------------------------------------------------------
# Datasets
# --------------------------------------------------------------------------------------------


def collate_batch(batch: Any) -> Any:
    """``collate_fn`` for the datasets here: ``__getitems__`` already returns whole batches."""
    return batch


def _apply_stats(name: str, x: np.ndarray, stats: FeatureStats | None) -> np.ndarray:
    if stats is not None and name in stats.mean:
        x = stats.normalize(name, x)
    return np.ascontiguousarray(x, dtype=np.float32)


def _normalized(cache: FeatureCache, name: str, rows: np.ndarray,
                stats: FeatureStats | None) -> np.ndarray:
    return _apply_stats(name, cache.rows(name, rows), stats)


#: A streamed dataset's block: (its sorted global rows, group -> normalised rows).
_Block = tuple[np.ndarray, dict[str, np.ndarray]]


class _Stream:
    """A streamed dataset's rows: the normalised rows its current batches need, read from the
    cache file (:meth:`FeatureCache.read`) when they change; nothing else of the groups is
    held.

    Attributes:
        rows: (k,) sorted global rows held.
        local: (N_total,) int64 position of each global row in the held arrays (-1: not held).
        data: group -> (rows held, dim) float32, normalised.
        reads: how many times rows were read (diagnostics and tests).
    """

    def __init__(self, cache: FeatureCache, groups: Sequence[str],
                 stats: FeatureStats | None) -> None:
        self.cache, self.groups, self.stats = cache, list(dict.fromkeys(groups)), stats
        self.rows = np.zeros(0, dtype=np.int64)
        self.local = np.full(cache.num_rows, -1, dtype=np.int64)
        self.data: dict[str, np.ndarray] = {}
        self.reads = 0

    def read(self, rows: np.ndarray) -> _Block:
        """(sorted unique rows, group -> their normalised values) read from the file; changes
        nothing held, so a helper thread can read the next block (:meth:`put` it)."""
        rows = np.unique(np.asarray(rows, dtype=np.int64))
        raw = self.cache.read(self.groups, rows)
        return rows, {g: _apply_stats(g, raw.pop(g), self.stats) for g in self.groups}

    def put(self, block: _Block) -> None:
        """Hold a block :meth:`read` returned (the previous one is let go)."""
        rows, self.data = block
        self.local.fill(-1)
        self.local[rows] = np.arange(len(rows))
        self.rows = rows
        self.reads += 1

    def hold(self, rows: np.ndarray) -> None:
        """Read and hold exactly these rows (the previous ones are let go)."""
        rows = np.unique(np.asarray(rows, dtype=np.int64))
        if np.array_equal(rows, self.rows):
            return
        self.data = {}  # let the previous block go before reading the next
        self.put(self.read(rows))

    def release(self) -> None:
        """Let the held rows go (the next batch reads its own)."""
        self.data, self.rows = {}, np.zeros(0, dtype=np.int64)
        self.local.fill(-1)

    def take(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        """group -> rows.shape + (dim,) normalised values at the given global rows (the whole
        sequences they lie in are read first when not all are held: an item taken alone)."""
        idx = self.local[rows]
        if (idx < 0).any():
            self.hold(self.cache.sequence_rows(np.unique(self.cache.row_sequence[rows])))
            idx = self.local[rows]
        return {g: v[idx] for g, v in self.data.items()}


class FrameDataset(torch.utils.data.Dataset):
    """Rows (t -> t+1 pairs) for PoseNet, the baseline and ContactNet.

    Item i is ``(inputs, targets)``: two dicts group -> float32 tensor (dim,), normalised with
    ``stats`` where it has the group. ``__getitems__`` returns the same with (B, dim) tensors.
    The rows are copied into memory (``inputs``, ``targets``), or, built with
    :meth:`streamed`, read from the cache file as batches need them (serve it with
    :class:`BlockLoader`).

    Args:
        cache: the feature cache.
        groups_in, groups_out: group names.
        indices: global row indices (e.g. ``cache.sequence_rows(train)``).
        stats: optional normalisation.
    """

    def __init__(self, cache: FeatureCache, groups_in: Sequence[str], groups_out: Sequence[str],
                 indices: np.ndarray, stats: FeatureStats | None = None) -> None:
        self.indices = np.asarray(indices, dtype=np.int64)
        self.cache, self.groups_in, self.groups_out = cache, list(groups_in), list(groups_out)
        self.stream: _Stream | None = None
        # Copy the needed rows once (normalised), so batches are plain slices of numpy arrays.
        self.inputs = {g: _normalized(cache, g, self.indices, stats) for g in groups_in}
        self.targets = {g: _normalized(cache, g, self.indices, stats) for g in groups_out}

    @classmethod
    def streamed(cls, cache: FeatureCache, groups_in: Sequence[str], groups_out: Sequence[str],
                 indices: np.ndarray, stats: FeatureStats | None = None) -> FrameDataset:
        """The same items as ``FrameDataset(cache, groups_in, groups_out, indices, stats)``
        with no rows copied: :class:`BlockLoader` reads a block of rows from the file at a
        time and serves its batches (an item taken alone reads its whole sequence), so memory
        holds a block, not the dataset. ``inputs`` and ``targets`` are empty."""
        ds = cls._shell(cache, groups_in, groups_out, indices)
        ds.stream = _Stream(cache, [*groups_in, *groups_out], stats)
        return ds

    @classmethod
    def _shell(cls, cache: FeatureCache, groups_in: Sequence[str], groups_out: Sequence[str],
               indices: np.ndarray) -> FrameDataset:
        """A dataset over ``indices`` with no rows yet (``inputs``, ``targets`` empty)."""
        ds = cls.__new__(cls)
        ds.indices = np.asarray(indices, dtype=np.int64)
        ds.cache, ds.groups_in, ds.groups_out = cache, list(groups_in), list(groups_out)
        ds.inputs, ds.targets, ds.stream = {}, {}, None
        return ds

    def item_rows(self, items: np.ndarray) -> np.ndarray:
        """(len(items), 1) int64 the global rows items need (one row each)."""
        return self.indices[np.asarray(items, dtype=np.int64)][:, None]

    @classmethod
    def splits(cls, cache: FeatureCache, groups_in: Sequence[str], groups_out: Sequence[str],
               index_sets: Sequence[np.ndarray], stats: FeatureStats | None = None
               ) -> list[FrameDataset]:
        """One dataset per set of rows (e.g. training and validation), the same as
        ``FrameDataset(cache, groups_in, groups_out, rows, stats)`` for each, built group by
        group: once every set has copied a group's rows the cache forgets the group
        (:meth:`FeatureCache.release`), so memory holds the datasets' copies and one group at
        a time, not the copies and the whole cache side by side."""
        out = [cls._shell(cache, groups_in, groups_out, rows) for rows in index_sets]
        for g in dict.fromkeys([*groups_in, *groups_out]):
            for ds in out:
                x = _normalized(cache, g, ds.indices, stats)
                if g in groups_in:
                    ds.inputs[g] = x
                if g in groups_out:  # shared with inputs when in both: batches copy rows
                    ds.targets[g] = x
            cache.release([g])
        for ds in out:
            ds.inputs = {g: ds.inputs[g] for g in groups_in}
            ds.targets = {g: ds.targets[g] for g in groups_out}
        return out

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, i: int) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        x, y = self.__getitems__([i])
        return {k: v[0] for k, v in x.items()}, {k: v[0] for k, v in y.items()}

    def __getitems__(self, idx: Sequence[int]
                     ) -> tuple[dict[str, torch.Tensor], dict[str, torch.Tensor]]:
        idx = np.asarray(idx, dtype=np.int64)
        if self.stream is not None:
            v = self.stream.take(self.indices[idx])
            return ({k: torch.from_numpy(v[k]) for k in self.groups_in},
                    {k: torch.from_numpy(v[k]) for k in self.groups_out})
        return ({k: torch.from_numpy(v[idx]) for k, v in self.inputs.items()},
                {k: torch.from_numpy(v[idx]) for k, v in self.targets.items()})


class WindowDataset(torch.utils.data.Dataset):
    """Fixed-length windows of consecutive rows inside one sequence (ControlNet training).

    Item i is a dict group -> float32 tensor (window, dim); ``__getitems__`` gives
    (B, window, dim). Windows start every ``stride`` rows (default ``window // 2``) and the
    last window of a sequence ends at its last row; sequences with fewer than ``window`` rows
    contribute none (they still serve PoseNet) and are counted in ``too_short``.

    Args:
        cache: the feature cache.
        window: frames per window (paper 60).
        stride: rows between window starts.
        sequences: sequence indices to draw from (default all).
        groups: groups to serve (default the ControlNet's inputs, targets and pose).
        stats: optional normalisation.
        rows: the groups already normalised over ``cache.sequence_rows(sequences)``, in that
            order (e.g. a :class:`FrameDataset`'s inputs and targets over the same rows): used
            as they are, not copied, so PoseNet's closed-loop windows share its training
            rows' memory. None: copied from the cache.
        stream: copy nothing; rows are read from the file a block at a time, as
            :meth:`FrameDataset.streamed` (serve it with :class:`BlockLoader`).
    """

    DEFAULT_GROUPS = ("joint_positions", "control_line", "hand_phases",
                      "next_control_positions", "next_control_phases")

    def __init__(self, cache: FeatureCache, window: int = 60, stride: int | None = None,
                 sequences: Iterable[int] | None = None, groups: Sequence[str] | None = None,
                 stats: FeatureStats | None = None,
                 rows: Mapping[str, np.ndarray] | None = None, stream: bool = False) -> None:
        if stream and rows is not None:
            raise ValueError("WindowDataset: a streamed dataset takes no rows")
        if window < 1:
            raise ValueError(f"window must be positive, got {window}")
        stride = stride or max(1, window // 2)
        seqs = list(range(cache.num_sequences) if sequences is None else sequences)
        groups = list(groups or self.DEFAULT_GROUPS)
        self.window = window
        starts: list[int] = []
        self.too_short = 0
        for s in seqs:
            lo, hi = int(cache.offsets[s]), int(cache.offsets[s + 1])
            if hi - lo < window:
                self.too_short += 1
                continue
            first = list(range(lo, hi - window + 1, stride))
            if first[-1] != hi - window:
                first.append(hi - window)
            starts.extend(first)
        self.starts = np.asarray(starts, dtype=np.int64)
        self.cache = cache
        self.stream = _Stream(cache, groups, stats) if stream else None
        if self.stream is not None:
            self.data: dict[str, np.ndarray] = {}
            return
        selected = cache.sequence_rows(seqs)
        # Keep the selected sequences' rows (normalised) and map global rows into them.
        self._local = np.full(cache.num_rows + 1, -1, dtype=np.int64)
        self._local[selected] = np.arange(len(selected))
        if rows is None:
            self.data = {g: _normalized(cache, g, selected, stats) for g in groups}
        else:
            bad = [g for g in groups if g not in rows or len(rows[g]) != len(selected)]
            if bad:
                raise ValueError(f"WindowDataset: rows given for {sorted(rows)} do not cover "
                                 f"{bad} over the sequences' {len(selected)} rows")
            self.data = {g: rows[g] for g in groups}

    def __len__(self) -> int:
        return len(self.starts)

    def item_rows(self, items: np.ndarray) -> np.ndarray:
        """(len(items), window) int64 the global rows items need (each window's rows)."""
        return self.starts[np.asarray(items, dtype=np.int64)][:, None] + np.arange(self.window)

    def _take(self, starts: np.ndarray) -> dict[str, torch.Tensor]:
        rows = starts[:, None] + np.arange(self.window)  # (B, window) global rows
        if self.stream is not None:
            return {k: torch.from_numpy(v) for k, v in self.stream.take(rows).items()}
        idx = self._local[rows]
        return {k: torch.from_numpy(v[idx]) for k, v in self.data.items()}

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {k: v[0] for k, v in self._take(self.starts[[i]]).items()}

    def __getitems__(self, idx: Sequence[int]) -> dict[str, torch.Tensor]:
        return self._take(self.starts[np.asarray(idx, dtype=np.int64)])


class BlockLoader:
    """Batches of a streamed :class:`FrameDataset` or :class:`WindowDataset`, a block of rows
    at a time (in place of a ``DataLoader``, which would read a batch's rows from all over the
    file).

    The items are cut into *pieces* by where they start in the cache: the items starting in
    the same ``piece_rows`` rows (by default one HDF5 chunk, :data:`CHUNK_ROWS`) are one
    piece. An epoch takes the pieces in order (``shuffle``: in a random order drawn from
    ``generator``) and groups them into blocks that need at least ``block_rows`` cache rows (a
    block is one file read of one slice per run of rows, ~18 KB a row for PoseNet); the items
    of a block, with those left over from the previous block when it did not end on a whole
    batch, are served in batches of ``batch_size`` (``shuffle``: in random order). Every item
    comes once an epoch, in ``ceil(len / batch_size)`` batches as from a ``DataLoader``
    without ``drop_last``. Shuffled, a block of 16,384 rows mixes about 64 pieces from all over
    the data (whole sequences would be a few dozen of them, ~350 rows each); a batch still mixes
    items from one block only. While a block's batches are served the next block is read in a
    helper thread, so memory holds two blocks.
    """

    def __init__(self, dataset: FrameDataset | WindowDataset, batch_size: int,
                 block_rows: int, shuffle: bool = False,
                 generator: torch.Generator | None = None, piece_rows: int = CHUNK_ROWS) -> None:
        if dataset.stream is None:
            raise ValueError("BlockLoader serves streamed datasets (FrameDataset.streamed, "
                             "WindowDataset(stream=True))")
        if batch_size < 1 or block_rows < 1 or piece_rows < 1:
            raise ValueError(f"batch_size, block_rows and piece_rows must be positive, got "
                             f"{batch_size}, {block_rows} and {piece_rows}")
        self.dataset, self.batch_size, self.block_rows = dataset, batch_size, block_rows
        self.shuffle, self.generator, self.piece_rows = shuffle, generator, piece_rows

    def __len__(self) -> int:
        return -(-len(self.dataset) // self.batch_size)

    def _perm(self, n: int) -> np.ndarray:
        if not self.shuffle:
            return np.arange(n)
        return torch.randperm(n, generator=self.generator).numpy()

    def plan(self) -> list[tuple[np.ndarray, list[np.ndarray]]]:
        """One epoch's order: [(sorted rows to hold, [item positions of each batch])] per
        block (draws from ``generator`` when shuffling)."""
        n = len(self.dataset)
        need = self.dataset.item_rows(np.arange(n))  # (n, k) rows each item needs
        by_start = np.argsort(need[:, 0], kind="stable")
        _, first, counts = np.unique(need[by_start, 0] // self.piece_rows, return_index=True,
                                     return_counts=True)
        pieces = [by_start[a:a + c] for a, c in zip(first.tolist(), counts.tolist(),
                                                      strict=True)]
        size = [len(np.unique(need[p])) for p in pieces]  # rows a piece needs
        order = self._perm(len(pieces))
        out: list[tuple[np.ndarray, list[np.ndarray]]] = []
        carry = np.zeros(0, dtype=np.int64)
        block: list[int] = []
        rows = 0
        for k, j in enumerate(order.tolist()):
            block.append(j)
            rows += size[j]
            if rows < self.block_rows and k + 1 < len(order):
                continue
            items = np.concatenate([carry, *[pieces[b] for b in block]])
            items = items[self._perm(len(items))]
            last = k + 1 == len(order)
            full = len(items) if last else len(items) // self.batch_size * self.batch_size
            out.append((np.unique(need[items]), [items[i:i + self.batch_size]
                                                 for i in range(0, full, self.batch_size)]))
            carry, block, rows = items[full:], [], 0
        return out

    def __iter__(self) -> Iterator[Any]:
        stream = self.dataset.stream
        assert stream is not None
        plan = self.plan()
        # The next block is read in a helper thread while the current one's batches train
        # (torch and most of HDF5's gzip work run without the GIL).
        try:
            with ThreadPoolExecutor(1) as pool:
                ahead = pool.submit(stream.read, plan[0][0]) if plan else None
                for k, (_, batches) in enumerate(plan):
                    assert ahead is not None
                    stream.put(ahead.result())  # the previous block is let go
                    ahead = pool.submit(stream.read, plan[k + 1][0]) if k + 1 < len(plan) \
                        else None
                    for b in batches:
                        yield self.dataset.__getitems__(b)
        finally:  # a loader holds no block between epochs
            stream.release()


def make_loader(dataset: torch.utils.data.Dataset, batch_size: int, shuffle: bool = False,
                generator: torch.Generator | None = None, block_rows: int = 0) -> Iterable[Any]:
    """Batches of one of the datasets here: a :class:`BlockLoader` for a streamed one (blocks
    of ``block_rows`` rows made of chunk-sized pieces), else a ``DataLoader`` slicing whole
    batches (:func:`collate_batch`)."""
    if getattr(dataset, "stream", None) is not None:
        return BlockLoader(dataset, batch_size, block_rows, shuffle, generator)  # type: ignore[arg-type]
    return torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=shuffle,
                                       generator=generator, collate_fn=collate_batch)


def stack_groups(values: Mapping[str, torch.Tensor], names: Sequence[str]) -> torch.Tensor:
    """Concatenate named (..., dim) tensors along the last axis in ``names`` order."""
    return torch.cat([values[n] for n in names], dim=-1)
