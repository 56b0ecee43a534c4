"""Shape library: chair and sofa meshes from ShapeNetCore v2 (or any folder of OBJ/PLY files),
repaired, put into couch's chair frame at a plausible metric scale, classified and cached.

Chair frame (the same as the simulator's chairs, ``tools/sim/chairs.py``): metres, +Y up, the
floor at y = 0, the seat centred on x = z = 0, the seat front facing +Z (a sitter looks towards
+Z; the backrest is at -Z).

Pipeline per mesh (:func:`load_shape_library`):

1. **Load** with trimesh (``process=False``, forced to one mesh). A file that cannot be read,
   has no vertices or no faces, non-finite coordinates or a near-zero extent along some axis
   (below 1e-4 of its bounding-box diagonal: a flat or empty shape) is skipped with a
   counted reason; nothing raises.
2. **Repair** with pymeshlab: merge duplicate vertices, drop duplicate and zero-area faces and
   unreferenced vertices, repair non-manifold edges and vertices, close small holes (up to
   :data:`MAX_HOLE_EDGES` edges). A mesh that is still not watertight, or that consists of
   several separate (typically intersecting) parts, is replaced by its CGAL
   alpha wrap (``generate_alpha_wrap``, alpha :data:`ALPHA_WRAP_PERCENT` % and offset
   :data:`ALPHA_WRAP_OFFSET_PERCENT` % of the bounding-box diagonal; ~0.5-2 s per chair), the
   robust watertight remesh for ShapeNet's multi-part, self-intersecting meshes. Each change is
   noted in :attr:`ShapeEntry.repaired`.
3. **Seat**: the largest upward-facing (normal·Y > :data:`UP_COS`) horizontal surface region with
   its height between 25 % and 65 % of the mesh height (area histogram over face heights, the
   peak height band kept, then its face-connected regions with at least 20 % of the largest
   region's area). When there is none, the same search above 65 % (a stool-like seat on top);
   no upward-facing surface at all: skipped as ``no seat``.
4. **Scale**: the seat height (above the lowest vertex) is set to one drawn uniformly from
   :data:`SEAT_HEIGHT_RANGE` of the shape's family (chair or sofa) with a generator seeded by
   ``seed`` and the shape id, so it is reproducible. The floor goes to y = 0 (the lowest vertex)
   and the seat's bounding-box centre to x = z = 0.
5. **Front**: the backrest is the surface more than :data:`BACK_MIN_RISE` m above the seat in a
   central strip behind the seat; of the four horizontal axis directions the one where that
   surface is most one-sided is the back, and the shape is turned about Y (by a multiple of 90°)
   so that the back is at -Z. Without a one-sided backrest (a stool-like seat) ShapeNet's own
   convention (front -Z, so the back at +Z) is assumed and a note is added to ``repaired``.
6. **Classify** (rules in :func:`classify_shape`) and **check plausibility**: seat width and
   depth at least :data:`MIN_SEAT_SIZE` m, overall width within :data:`WIDTH_RANGE` of the
   category, overall depth and height within :data:`MAX_DEPTH`/:data:`MAX_HEIGHT`; otherwise
   the shape is skipped as ``implausible size`` (a wrong-scale or wrongly proportioned mesh).

Cache: each cleaned mesh is written to ``cache_dir`` as a :mod:`couch.records` HDF5 file of its
:class:`ShapeEntry` (a skip as one holding the reason; nothing pickled), keyed by
the source's resolved path, size and mtime, the seed and :data:`CACHE_VERSION`, written
atomically. The default cache folder is
``$XDG_CACHE_HOME/couch/shapes/<hash of root>`` (``~/.cache/...``), never inside ``root``, which
may be read-only.
"""

from __future__ import annotations

import hashlib
import logging
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
import pymeshlab
import trimesh
from tqdm import tqdm

from couch.records import RecordError, read_record, write_record

__all__ = [
    "ALPHA_WRAP_PERCENT",
    "CATEGORIES",
    "CHAIR_SYNSET",
    "SEAT_HEIGHT_RANGE",
    "SOFA_SYNSET",
    "WIDTH_RANGE",
    "ShapeEntry",
    "ShapeLibrary",
    "classify_shape",
    "load_shape_library",
]

log = logging.getLogger(__name__)

CATEGORIES = ("straight", "armchair", "sofa")
CHAIR_SYNSET = "03001627"
SOFA_SYNSET = "04256520"
_SYNSETS = (CHAIR_SYNSET, SOFA_SYNSET)
_MESH_SUFFIXES = (".obj", ".ply")

CACHE_VERSION = 1
"""Bumped whenever the processing changes, which invalidates every cached entry."""

MAX_HOLE_EDGES = 30
ALPHA_WRAP_PERCENT = 1.0
ALPHA_WRAP_OFFSET_PERCENT = 0.1
UP_COS = 0.9
"""Faces whose unit normal has a Y component above this count as upward-facing (within ~25°)."""
SEAT_BAND = (0.25, 0.65)
"""The seat lies between these fractions of the mesh height above its lowest point."""

SEAT_HEIGHT_RANGE = {"chair": (0.40, 0.48), "sofa": (0.38, 0.45)}
"""Seat heights (m) drawn per shape, by family (straight chairs and armchairs are "chair")."""
WIDTH_RANGE = {"straight": (0.30, 0.90), "armchair": (0.40, 1.10), "sofa": (1.10, 2.60)}
"""Plausible overall widths (m, along X) per category; outside: skipped as implausible."""
MIN_SEAT_SIZE = 0.25
MAX_DEPTH = 1.4
MAX_HEIGHT = 2.0
BACK_MIN_RISE = 0.15
"""Backrest surface: more than this (m) above the seat plane."""
BACK_MIN_AREA = 0.01
"""Backrest: at least this much one-sided surface area (m²) behind the seat."""
SOFA_WIDTH_PER_SEAT_HEIGHT = 2.5
"""Sofa when overall width / seat height ≥ this (≈ 1.1 m wide at a 0.44 m seat)."""
ARMREST_RISE = (0.12, 0.38)
"""Armrest tops: upward-facing surface this far (m) above the seat plane (nominal 0.15-0.35)."""


# --------------------------------------------------------------------------------------------
# Data
# --------------------------------------------------------------------------------------------

@dataclass(eq=False)
class ShapeEntry:
    """One cleaned chair-like mesh in the chair frame (see module doc).

    ``vertices`` (V, 3) float64 metres, ``faces`` (F, 3) int64 (closed, outward-oriented);
    ``seat_height`` the seat surface above the floor (m); ``width``/``depth``/``height`` the
    overall bounding-box extents along X/Z/Y (m); ``seat_width``/``seat_depth`` the extents of the
    seat surface region (m); ``scale`` the factor applied to the (normalised) source mesh;
    ``repaired`` human-readable notes on what was fixed or assumed; ``from_cache`` whether this
    entry was read from the cache rather than computed.
    """

    id: str
    source: Path
    category: str
    vertices: np.ndarray
    faces: np.ndarray
    seat_height: float
    width: float
    depth: float
    scale: float
    repaired: list[str] = field(default_factory=list)
    height: float = 0.0
    seat_width: float = 0.0
    seat_depth: float = 0.0
    has_back: bool = True
    from_cache: bool = False


@dataclass
class ShapeLibrary:
    """The usable shapes (``entries``) and the rejected sources (``skipped``: (id or path,
    reason) with the reason ``"<kind>: <details>"``, e.g. ``"non-finite: ..."``)."""

    entries: list[ShapeEntry] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)

    def by_category(self, category: str) -> list[ShapeEntry]:
        return [e for e in self.entries if e.category == category]

    def summary(self) -> str:
        """One line per category with its count, then the skips counted by reason kind."""
        counts = Counter(e.category for e in self.entries)
        lines = [f"{len(self.entries)} shapes: "
                 + ", ".join(f"{counts.get(c, 0)} {c}" for c in CATEGORIES)]
        reasons = Counter(reason.split(":", 1)[0] for _, reason in self.skipped)
        lines.append(f"{len(self.skipped)} skipped"
                     + (": " + ", ".join(f"{n} {r}" for r, n in sorted(reasons.items()))
                        if reasons else ""))
        return "\n".join(lines)


class _Skip(Exception):
    """A source mesh is unusable; the message is the reason ``"<kind>: <details>"``."""


# --------------------------------------------------------------------------------------------
# Discovery
# --------------------------------------------------------------------------------------------

def _find_sources(root: Path, cache_dir: Path) -> tuple[list[tuple[str, Path]],
                                                        list[tuple[str, str]]]:
    """(id, mesh path) pairs under ``root`` sorted by id, and the model folders without a mesh.

    ShapeNetCore v2 layout when ``root`` has a chair or sofa synset folder (other synsets are
    ignored); otherwise every ``.obj``/``.ply`` file below ``root`` (hidden folders and the cache
    skipped), the id being its path relative to ``root`` without the suffix.
    """
    synsets = [root / s for s in _SYNSETS if (root / s).is_dir()]
    sources: list[tuple[str, Path]] = []
    missing: list[tuple[str, str]] = []
    if synsets:
        for syn in synsets:
            for model in sorted(p for p in syn.iterdir() if p.is_dir()):
                mesh = model / "models" / "model_normalized.obj"
                if mesh.is_file():
                    sources.append((model.name, mesh))
                else:
                    missing.append((model.name, f"unreadable: {mesh} does not exist"))
    else:
        cache_dir = cache_dir.resolve()
        for path in root.rglob("*"):
            rel = path.relative_to(root)
            if (path.suffix.lower() not in _MESH_SUFFIXES or not path.is_file()
                    or any(part.startswith(".") for part in rel.parts)
                    or path.resolve().is_relative_to(cache_dir)):
                continue
            sources.append((rel.with_suffix("").as_posix(), path))
    sources.sort(key=lambda s: (s[0], str(s[1])))
    return sources, missing


def _default_cache_dir(root: Path) -> Path:
    base = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache")
    digest = hashlib.sha256(str(root.resolve()).encode()).hexdigest()[:16]
    return base / "couch" / "shapes" / digest


def _cache_key(path: Path, seed: int) -> str:
    st = path.stat()
    text = f"{path.resolve()}|{st.st_size}|{st.st_mtime_ns}|{seed}|{CACHE_VERSION}"
    return hashlib.sha256(text.encode()).hexdigest()[:24]


# --------------------------------------------------------------------------------------------
# Loading and repair
# --------------------------------------------------------------------------------------------

def _load(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float64 and faces (F, 3) int64 of ``path``, or :class:`_Skip`."""
    try:
        mesh = trimesh.load(path, file_type=path.suffix.lower()[1:], force="mesh",
                            process=False)
    except Exception as exc:   # trimesh raises many kinds for malformed files
        raise _Skip(f"unreadable: {type(exc).__name__}: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh):
        raise _Skip("empty: no triangle mesh in the file")
    v = np.asarray(mesh.vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(mesh.faces, dtype=np.int64).reshape(-1, 3)
    if len(v) == 0:
        raise _Skip("no faces: vertices only" if _has_points(path) else "empty: no vertices")
    if len(f) == 0:
        raise _Skip("no faces: vertices only")
    if not np.all(np.isfinite(v)):
        raise _Skip(f"non-finite: {int((~np.isfinite(v)).any(1).sum())} vertices with NaN/inf")
    if f.min() < 0 or f.max() >= len(v):
        raise _Skip("unreadable: face indices out of range")
    used = v[np.unique(f)]
    ext = np.ptp(used, axis=0)
    diag = float(np.linalg.norm(ext))
    if diag < 1e-9 or ext.min() < 1e-4 * diag:
        raise _Skip(f"degenerate: extent {np.array2string(ext, precision=3)}")
    return v, f


def _has_points(path: Path) -> bool:
    """Whether ``path`` holds vertices (e.g. a point cloud) though no triangles were found."""
    try:
        geom = trimesh.load(path, file_type=path.suffix.lower()[1:], process=False)
    except Exception:   # unreadable: treat as no points
        return False
    return len(getattr(geom, "vertices", ())) > 0


def _repair(v: np.ndarray, f: np.ndarray, notes: list[str]) -> trimesh.Trimesh:
    """Watertight, outward-oriented mesh from (v, f) with pymeshlab; appends to ``notes``."""
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=v, face_matrix=f.astype(np.int32)))

    def counts() -> tuple[int, int]:
        m = ms.current_mesh()
        return m.vertex_number(), m.face_number()

    steps = [
        ("meshing_remove_duplicate_vertices", {}, "merged {dv} duplicate vertices"),
        ("meshing_remove_duplicate_faces", {}, "removed {df} duplicate faces"),
        ("meshing_remove_null_faces", {}, "removed {df} zero-area faces"),
        ("meshing_remove_unreferenced_vertices", {}, "removed {dv} unreferenced vertices"),
        ("meshing_repair_non_manifold_edges", {}, "removed {df} faces on non-manifold edges"),
        ("meshing_repair_non_manifold_vertices", {}, "split {dv} non-manifold vertices"),
        ("meshing_close_holes", {"maxholesize": MAX_HOLE_EDGES},
         "closed holes with {df} faces"),
    ]
    for name, kwargs, note in steps:
        nv, nf = counts()
        try:
            getattr(ms, name)(**kwargs)
        except pymeshlab.PyMeshLabException as exc:
            notes.append(f"{name} failed ({exc})")
            continue
        nv2, nf2 = counts()
        if (nv2, nf2) != (nv, nf):
            notes.append(note.format(dv=abs(nv - nv2), df=abs(nf - nf2)))
    m = ms.current_mesh()
    if m.face_number() == 0:
        raise _Skip("degenerate: no faces left after removing duplicates")
    mesh = trimesh.Trimesh(m.vertex_matrix().astype(np.float64),
                           m.face_matrix().astype(np.int64), process=False)
    parts = int(ms.get_topological_measures()["connected_components_number"])
    if not mesh.is_watertight or parts > 1:
        ms.generate_alpha_wrap(alpha=pymeshlab.PercentageValue(ALPHA_WRAP_PERCENT),
                               offset=pymeshlab.PercentageValue(ALPHA_WRAP_OFFSET_PERCENT))
        m = ms.current_mesh()
        mesh = trimesh.Trimesh(m.vertex_matrix().astype(np.float64),
                               m.face_matrix().astype(np.int64), process=False)
        why = "not watertight after cleaning" if parts == 1 else f"{parts} separate parts"
        notes.append(f"{why}: replaced by its alpha wrap ({len(mesh.faces)} faces)")
        if not mesh.is_watertight:
            raise _Skip("repair failed: the alpha wrap is not watertight")
    if not mesh.is_winding_consistent or mesh.volume < 0:
        mesh.fix_normals()
        notes.append("re-oriented faces outwards")
    return mesh


# --------------------------------------------------------------------------------------------
# Geometry: seat, back, armrests
# --------------------------------------------------------------------------------------------

def _seat_faces(mesh: trimesh.Trimesh) -> tuple[np.ndarray, float]:
    """Face indices of the seat region and its area-weighted mean height (mesh units)."""
    normals, areas = mesh.face_normals, mesh.area_faces
    y = mesh.triangles_center[:, 1]
    ymin, ymax = mesh.bounds[:, 1]
    height = ymax - ymin
    lo, hi = ymin + SEAT_BAND[0] * height, ymin + SEAT_BAND[1] * height
    up = (normals[:, 1] > UP_COS) & (areas > 0)
    cand = np.flatnonzero(up & (y >= lo) & (y <= hi))
    if len(cand) == 0:
        # A stool-like seat is the top of the shape: fall back to the upper part.
        lo, hi = hi, ymax
        cand = np.flatnonzero(up & (y >= lo))
    if len(cand) == 0:
        raise _Skip("no seat: no upward-facing surface above 25% of the height")
    bin_w = 0.01 * height
    hist, edges = np.histogram(y[cand], bins=max(1, round((hi - lo) / bin_w)), range=(lo, hi),
                               weights=areas[cand])
    # Smooth over neighbouring bins so that a seat straddling a bin edge is not split.
    smooth = np.convolve(hist, np.ones(3), mode="same")
    peak = int(np.argmax(smooth))
    band_lo, band_hi = edges[max(peak - 1, 0)], edges[min(peak + 2, len(edges) - 1)]
    band = cand[(y[cand] >= band_lo) & (y[cand] <= band_hi)]
    comps = trimesh.graph.connected_components(mesh.face_adjacency, nodes=band,
                                               min_len=1, engine="scipy")
    comps = [np.asarray(c, dtype=np.int64) for c in comps]
    if not comps:
        comps = [band]
    comp_area = np.array([areas[c].sum() for c in comps])
    keep = np.concatenate([c for c, a in zip(comps, comp_area, strict=True)
                           if a >= 0.2 * comp_area.max()])
    seat_y = float(np.average(y[keep], weights=areas[keep]))
    return keep, seat_y


def _seat_box(vertices: np.ndarray, faces: np.ndarray, seat: np.ndarray) -> np.ndarray:
    """(2, 2) min/max of the seat region's X and Z: ``[[xmin, zmin], [xmax, zmax]]``."""
    pts = vertices[np.unique(faces[seat])][:, [0, 2]]
    return np.stack([pts.min(0), pts.max(0)])


_YAW_TO_BACK_NEG_Z = {
    # back direction (axis, sign) -> rotation about Y taking it to -Z (det +1: faces kept)
    (2, -1): np.eye(3),
    (2, 1): np.diag([-1.0, 1.0, -1.0]),
    (0, 1): np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]),
    (0, -1): np.array([[0.0, 0.0, -1.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]),
}


def _surface_samples(mesh: trimesh.Trimesh, rng: np.random.Generator, count: int = 20000
                     ) -> tuple[np.ndarray, np.ndarray, float]:
    """Area-uniform surface points (N, 3), their face indices (N,), and the area per point."""
    areas = mesh.area_faces
    total = float(areas.sum())
    face = rng.choice(len(areas), size=count, p=areas / total)
    r = rng.random((count, 2))
    flip = r.sum(1) > 1
    r[flip] = 1 - r[flip]
    tri = mesh.triangles[face]
    pts = tri[:, 0] + r[:, :1] * (tri[:, 1] - tri[:, 0]) + r[:, 1:] * (tri[:, 2] - tri[:, 0])
    return pts, face, total / count


def _back_direction(pts: np.ndarray, dA: float, seat_h: float, box: np.ndarray
                    ) -> tuple[int, int] | None:
    """(axis 0|2, sign ±1) of the backrest relative to the seat (seat centred on x = z = 0),
    or None when no one-sided surface rises more than :data:`BACK_MIN_RISE` above the seat."""
    high = pts[pts[:, 1] > seat_h + BACK_MIN_RISE]
    best: tuple[float, tuple[int, int]] | None = None
    for axis in (0, 2):
        lat = 2 - axis   # the other horizontal axis
        k = 0 if axis == 0 else 1
        lat_k = 1 - k
        half_lat = 0.5 * (box[1, lat_k] - box[0, lat_k])
        strip = high[np.abs(high[:, lat]) < 0.6 * half_lat]
        side = {s: float((s * strip[:, axis] > 0.25 * s * box[(s + 1) // 2, k]).sum()) * dA
                for s in (-1, 1)}
        for s in (-1, 1):
            score = side[s] - side[-s]
            if side[s] >= BACK_MIN_AREA and score >= 0.5 * side[s] and (
                    best is None or score > best[0]):
                best = (score, (axis, s))
    return None if best is None else best[1]


def _armrest_tops(pts: np.ndarray, normals: np.ndarray, seat_h: float, box: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Boolean masks (N,) of the points that may lie on an armrest top, on the +X (the sitter's
    left) and the -X side: upward-facing (normal·Y > 0.7), :data:`ARMREST_RISE` above the seat
    plane ``seat_h``, beside the seat's lateral edges (8 cm inside to 30 cm outside the seat box
    ``box`` [[xmin, zmin], [xmax, zmax]]), from 5 cm in front of the seat's rear edge to 10 cm
    beyond its front edge. ``pts`` (N, 3) surface points, ``normals`` (N, 3) unit."""
    rise = pts[:, 1] - seat_h
    (x0, z0), (x1, z1) = box
    sel = ((normals[:, 1] > 0.7) & (rise > ARMREST_RISE[0]) & (rise < ARMREST_RISE[1])
           & (pts[:, 2] > z0 + 0.05) & (pts[:, 2] < z1 + 0.1))
    left = sel & (pts[:, 0] > x1 - 0.08) & (pts[:, 0] < x1 + 0.30)
    right = sel & (pts[:, 0] > x0 - 0.30) & (pts[:, 0] < x0 + 0.08)
    return left, right


def _has_armrests(pts: np.ndarray, normals: np.ndarray, dA: float, seat_h: float,
                  box: np.ndarray) -> bool:
    """Armrest tops (:func:`_armrest_tops`) on both lateral sides, each with ≥ 0.005 m² of
    area (``dA`` m² per sample point) spanning ≥ 30% of the seat depth."""
    depth = box[1, 1] - box[0, 1]
    for mask in _armrest_tops(pts, normals, seat_h, box):
        side = pts[mask]
        if len(side) * dA < 0.005 or np.ptp(side[:, 2]) < 0.3 * depth:
            return False
    return True


def classify_shape(width: float, seat_height: float, seat_width: float, seat_depth: float,
                   has_armrests: bool) -> str:
    """Category of a chair-like shape from its geometry (metres).

    * ``"sofa"``: overall width ≥ :data:`SOFA_WIDTH_PER_SEAT_HEIGHT` × seat height (≈ 1.1 m at
      a 0.44 m seat; the ratio keeps the rule independent of the drawn seat height) or a seat at
      least twice as wide as deep;
    * ``"armchair"``: armrests, i.e. upward-facing surface 0.12-0.38 m above the seat plane on
      both the left and right, near the seat's lateral edges, over ≥ 30 % of the seat depth;
    * ``"straight"``: anything else.
    """
    if width >= SOFA_WIDTH_PER_SEAT_HEIGHT * seat_height or seat_width >= 2.0 * seat_depth:
        return "sofa"
    return "armchair" if has_armrests else "straight"


def _shape_rng(seed: int, shape_id: str) -> np.random.Generator:
    digest = hashlib.sha256(shape_id.encode()).digest()
    return np.random.default_rng([int(seed), int.from_bytes(digest[:8], "little")])


def _process(shape_id: str, path: Path, seed: int) -> ShapeEntry:
    """Load, repair, scale, orient and classify one mesh (see module doc); :class:`_Skip`."""
    v, f = _load(path)
    notes: list[str] = []
    mesh = _repair(v, f, notes)
    seat, seat_y = _seat_faces(mesh)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    f = np.asarray(mesh.faces, dtype=np.int64)
    ymin = float(v[:, 1].min())
    rise = seat_y - ymin
    box = _seat_box(v, f, seat)
    width0 = float(np.ptp(v[:, 0]))
    depth0 = float(np.ptp(v[:, 2]))
    # Family (chair or sofa) before the seat height is drawn: the sofa rule is scale-free.
    seat_w0, seat_d0 = np.ptp(box, axis=0)
    wide = max(width0, depth0) / rise >= SOFA_WIDTH_PER_SEAT_HEIGHT or (
        max(seat_w0, seat_d0) >= 2.0 * min(seat_w0, seat_d0))
    rng = _shape_rng(seed, shape_id)
    seat_h = float(rng.uniform(*SEAT_HEIGHT_RANGE["sofa" if wide else "chair"]))
    scale = seat_h / rise
    centre = np.array([box[:, 0].mean(), ymin, box[:, 1].mean()])
    v = (v - centre) * scale
    mesh = trimesh.Trimesh(v, f, process=False)
    pts, face, dA = _surface_samples(mesh, rng)
    back = _back_direction(pts, dA, seat_h, _seat_box(v, f, seat))
    has_back = back is not None
    if back is None:
        back = (2, 1)   # ShapeNet: front -Z, so the back is at +Z
        notes.append("no backrest found: assumed ShapeNet's front (-Z)")
    rot = _YAW_TO_BACK_NEG_Z[back]
    v = v @ rot.T
    mesh = trimesh.Trimesh(v, f, process=False)
    box = _seat_box(v, f, seat)
    seat_w, seat_d = (float(d) for d in np.ptp(box, axis=0))
    width, depth, height = (float(d) for d in np.ptp(v, axis=0)[[0, 2, 1]])
    arms = _has_armrests(pts @ rot.T, mesh.face_normals[face], dA, seat_h, box)
    category = classify_shape(width, seat_h, seat_w, seat_d, arms)

    problems = []
    if min(seat_w, seat_d) < MIN_SEAT_SIZE:
        problems.append(f"seat {seat_w:.2f} x {seat_d:.2f} m (< {MIN_SEAT_SIZE} m)")
    lo, hi = WIDTH_RANGE[category]
    if not lo <= width <= hi:
        problems.append(f"width {width:.2f} m outside [{lo}, {hi}] m for a {category}")
    if depth > MAX_DEPTH:
        problems.append(f"depth {depth:.2f} m > {MAX_DEPTH} m")
    if height > MAX_HEIGHT:
        problems.append(f"height {height:.2f} m > {MAX_HEIGHT} m")
    if problems:
        raise _Skip(f"implausible size: at seat height {seat_h:.2f} m, " + "; ".join(problems))
    return ShapeEntry(id=shape_id, source=path, category=category, vertices=v, faces=f,
                      seat_height=seat_h, width=width, depth=depth, scale=float(scale),
                      repaired=notes, height=height, seat_width=seat_w, seat_depth=seat_d,
                      has_back=has_back)


# --------------------------------------------------------------------------------------------
# Cache
# --------------------------------------------------------------------------------------------

@dataclass
class _Skipped:
    """A cached skip: why the source cannot be used."""

    reason: str


def _cache_read(cache_dir: Path, key: str) -> ShapeEntry | str | None:
    """The cached entry, the cached skip reason, or None (not cached or unreadable)."""
    path = cache_dir / f"{key}.h5"
    if not path.is_file():
        return None
    try:
        with h5py.File(path, "r") as h5:
            kind = h5.attrs.get("class")
        if kind == _Skipped.__qualname__:
            return read_record(path, _Skipped).reason
        entry = read_record(path, ShapeEntry)
    except (OSError, RecordError) as exc:
        log.warning("shape cache %s unreadable (%s); recomputing", path, exc)
        return None
    entry.from_cache = True
    return entry


def _cache_write(cache_dir: Path, key: str, result: ShapeEntry | str) -> None:
    """Keep a cleaned mesh (or why the source was skipped) as a :mod:`couch.records` file."""
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        write_record(cache_dir / f"{key}.h5",
                     _Skipped(result) if isinstance(result, str) else result)
    except OSError as exc:   # a read-only or full cache must not stop the library
        log.warning("cannot write shape cache in %s (%s)", cache_dir, exc)


# --------------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------------

def load_shape_library(root: str | os.PathLike, *, cache_dir: str | os.PathLike | None = None,
                       seed: int = 0, limit: int | None = None,
                       progress: bool = False) -> ShapeLibrary:
    """Read, repair, scale, orient and classify every chair/sofa mesh under ``root``.

    ``root``: a ShapeNetCore v2 folder (``<synsetId>/<modelId>/models/model_normalized.obj``;
    synsets chair 03001627 and sofa 04256520, others ignored; ``taxonomy.json`` not needed) or
    any folder of ``.obj``/``.ply`` files (searched recursively). ``cache_dir``: where cleaned
    meshes are kept (default ``~/.cache/couch/shapes/<hash of root>``); ``seed``: seeds the
    per-shape seat heights (with the shape id); ``limit``: process only the first ``limit``
    sources (sorted by id); ``progress``: a tqdm bar.

    Never raises for a bad mesh: it lands in :attr:`ShapeLibrary.skipped` with its reason (see
    module doc). Raises ``FileNotFoundError`` when ``root`` is not a folder.
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: shape library folder does not exist")
    cache = Path(cache_dir) if cache_dir is not None else _default_cache_dir(root)
    sources, missing = _find_sources(root, cache)
    if limit is not None:
        sources = sources[:limit]
    lib = ShapeLibrary(skipped=list(missing))
    for shape_id, path in tqdm(sources, desc="shapes", unit="mesh", disable=not progress):
        try:
            key = _cache_key(path, seed)
        except OSError as exc:
            lib.skipped.append((shape_id, f"unreadable: {exc}"))
            continue
        result = _cache_read(cache, key)
        if result is None:
            try:
                result = _process(shape_id, path, seed)
            except _Skip as exc:
                result = str(exc)
            except Exception as exc:   # never crash on one bad mesh
                log.exception("shape %s (%s) failed", shape_id, path)
                result = f"error: {type(exc).__name__}: {exc}"
            # Unexpected errors are not cached: they are retried next time.
            if not (isinstance(result, str) and result.startswith("error:")):
                _cache_write(cache, key, result)
        if isinstance(result, str):
            lib.skipped.append((shape_id, result))
        else:
            lib.entries.append(result)
    return lib
