"""Read and write the P3 matching format of the WPI / UPenn "Buildings built in minutes" SfM project.

A P3 folder holds ``1.png`` (or ``1.jpg``) ... ``M.png``, ``calibration.txt`` with K, and
``matching1.txt`` ... ``matching{M-1}.txt``. ``matching{i}.txt`` lists features of image *i*
and their matches in the images after it::

    nFeatures: N
    k R G B u_i v_i j1 u_j1 v_j1 [j2 u_j2 v_j2 ...]

``k`` counts the images the feature is seen in *including image i*, so a row has
``5 + 3 (k - 1)`` numbers after ``k``. Image ids are 1-based; ``(u, v)`` are pixels (column,
row), origin at the top-left corner (the kit's convention, see :mod:`course_lib.conventions`).

What the reader copes with (all found in the course's own files, see ``SOURCES.md``):

* CRLF or LF line endings, trailing spaces, blank lines, no final newline;
* ``nFeatures`` that is *not* the number of rows (WPI: the number of SIFT features detected):
  rows are read until the end of the file; the header line is optional;
* the same correspondence on several rows (kept once: ``matches`` holds *unique* correspondences);
* the same feature of image *i* on several rows with different sets of *j*;
* feature identity across files given only by equal coordinates: tracks are the connected
  components of the graph whose nodes are ``(image, u, v)`` and whose edges are the
  correspondences (union-find);
* calibration files as three rows of three numbers or in MATLAB syntax ``K = [a b c; d e f; g h i]``.

**Inconsistent tracks.** Real matches contain outliers, so a connected component can hold two
*different* features of the same image (e.g. feature A of image 1 is matched to B in image 3 on
one row and to B' in image 3 on another). A track holds only one observation per image, so the
reader applies this rule to such a component:

1. in every image that holds more than one of its features, keep the feature with strictly the
   most (unique) correspondences inside the component and drop the others; on a tie drop them all;
2. the kept features may fall apart into several pieces (connected by correspondences between
   kept features); every piece with at least two observations becomes a track.

The dropped observations are counted in :attr:`P3Data.stats` (``inconsistent_components``,
``dropped_observations``). ``matches`` is not affected by this rule (it holds the pairs "as
given"); a correspondence whose two features are not both in the same track has ``track_id = -1``.

Malformed input raises :class:`~course_lib.validate.KitInputError` naming the file and the line.

Introduced in ``notebooks/01_fundamental_matrix.ipynb``.
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from course_lib.data.camera import read_camera
from course_lib.data.two_view import read_two_view_geometries
from course_lib.validate import KitInputError, file_in, intrinsics

__all__ = ["PairMatches", "P3Data", "read_calibration", "read_p3", "write_p3", "tracks_from_pairs", "UnionFind", "IMAGE_EXTENSIONS",
           "SOURCE_NAMES_FILE", "write_source_names", "read_source_names"]

#: Image file extensions the reader looks for, in order of preference (``1.png`` before ``1.jpg``).
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".bmp")

#: The file in which ``match`` keeps the photos' own names beside their P3 names (:func:`write_source_names`).
SOURCE_NAMES_FILE = "source_names.json"

_MATCHING_RE = re.compile(r"^matching(\d+)\.txt$", re.IGNORECASE)
_HEADER_RE = re.compile(r"^\s*nFeatures\s*:?\s*(\S*)\s*$", re.IGNORECASE)


@dataclass
class PairMatches:
    """Unique correspondences between images ``i < j`` as given in ``matching{i+1}.txt``.

    Attributes:
        x1: ``(N, 2)`` pixels in image i.
        x2: ``(N, 2)`` pixels in image j.
        rgb: ``(N, 3)`` uint8 colour of the feature in image i.
        track_ids: ``(N,)`` int index into :attr:`P3Data.track_uv`, -1 where the correspondence
            is not part of a (consistent) track.
    """

    x1: np.ndarray
    x2: np.ndarray
    rgb: np.ndarray
    track_ids: np.ndarray

    def __len__(self) -> int:
        return int(self.x1.shape[0])


def _empty_pair() -> PairMatches:
    return PairMatches(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 3), np.uint8), np.zeros(0, int))


@dataclass
class P3Data:
    """The content of a P3 folder, with 0-based image indices.

    Attributes:
        folder: the folder it was read from.
        image_names: ``M`` file names; index ``i`` is P3 image id ``i + 1``.
        K: ``(3, 3)`` intrinsics (pixels).
        track_uv: ``(T, M, 2)`` float pixels of every track in every image, NaN where unseen.
        track_rgb: ``(T, 3)`` uint8 colour of each track (from the row of its first image).
        matches: ``{(i, j): PairMatches}`` for ``i < j``; pairs without any correspondence are absent
            (use :meth:`pair`, which returns an empty :class:`PairMatches` for them).
        stats: counts of what the reader found and fixed (rows, duplicates, dropped observations ...).
        two_view: ``{(i, j): F (3, 3)}`` of the pairs that ``match`` verified, where the folder
            carries them (:func:`course_lib.data.two_view.read_two_view_geometries`), else None.
        camera: the :class:`course_lib.data.camera.CameraPrior` of :data:`course_lib.data.camera.CAMERA_FILE`
            where the folder has one (K estimated, to be refined), else None (K from calibration.txt, fixed).
        source_names: ``M`` names of the photos ``match`` made the folder from (``IMG_1234.JPG``,
            ``sub/frame_0001.png``), where the folder carries :data:`SOURCE_NAMES_FILE`, else None;
            :attr:`photo_names` is what the outputs of ``sfm`` call the images.
    """

    folder: Path
    image_names: list[str]
    K: np.ndarray
    track_uv: np.ndarray
    track_rgb: np.ndarray
    matches: dict
    stats: dict = field(default_factory=dict)
    two_view: dict | None = None
    camera: object = None
    source_names: list | None = None
    _images: dict = field(default_factory=dict, repr=False)

    @property
    def photo_names(self) -> list[str]:
        """``M`` names of the images as the user knows them: :attr:`source_names` where known, else :attr:`image_names`."""
        return list(self.source_names) if self.source_names is not None else list(self.image_names)

    @property
    def n_images(self) -> int:
        """M, the number of images."""
        return len(self.image_names)

    @property
    def n_tracks(self) -> int:
        """T, the number of tracks."""
        return int(self.track_uv.shape[0])

    def pair(self, i: int, j: int) -> PairMatches:
        """Correspondences of images ``i`` and ``j`` (0-based, either order; empty if none).

        For ``i > j`` the returned ``x1`` is in image i (the columns are swapped for you).
        """
        for idx in (i, j):
            if not 0 <= idx < self.n_images:
                raise KitInputError(f"image index {idx} out of range: this folder has {self.n_images} images (0..{self.n_images - 1})")
        if i == j:
            raise KitInputError(f"pair ({i}, {j}): an image has no correspondences with itself")
        pm = self.matches.get((min(i, j), max(i, j)), _empty_pair())
        return pm if i < j else PairMatches(pm.x2, pm.x1, pm.rgb, pm.track_ids)

    def image_path(self, i: int) -> Path:
        """Path of image ``i`` (0-based)."""
        if not 0 <= i < self.n_images:
            raise KitInputError(f"image index {i} out of range: this folder has {self.n_images} images (0..{self.n_images - 1})")
        return Path(self.folder) / self.image_names[i]

    def image(self, i: int) -> np.ndarray:
        """Image ``i`` (0-based) as ``(H, W, 3)`` uint8 RGB, read on first use and cached."""
        if i not in self._images:
            import cv2

            p = self.image_path(i)
            if not p.is_file():
                raise KitInputError(f"image {i} (P3 id {i + 1}) not found: {p} (the matches can be used without it)")
            bgr = cv2.imread(str(p), cv2.IMREAD_COLOR)
            if bgr is None:
                raise KitInputError(f"could not decode image {p}: is it a valid PNG/JPEG file?")
            self._images[i] = np.ascontiguousarray(bgr[:, :, ::-1])
        return self._images[i]

    @property
    def image_size(self) -> tuple[int, int]:
        """``(W, H)`` of the images in pixels (read from the first image)."""
        H, W = self.image(0).shape[:2]
        return (int(W), int(H))


# --------------------------------------------------------------------------------------------
# calibration


def _parse_calibration_text(text: str, name: str) -> np.ndarray:
    body = text
    if "=" in body:  # MATLAB syntax: K = [a b c; d e f; g h i]
        body = body.split("=", 1)[1]
    body = body.replace("[", " ").replace("]", " ").replace(";", " ").replace(",", " ")
    tokens = body.split()
    values = []
    for tok in tokens:
        try:
            values.append(float(tok))
        except ValueError:
            raise KitInputError(f"{name}: cannot read {tok!r} as a number; expected 3 rows of 3 numbers or 'K = [a b c; d e f; g h i]'") from None
    if len(values) != 9:
        raise KitInputError(f"{name}: found {len(values)} numbers, expected the 9 entries of K (3 rows of 3 numbers or 'K = [a b c; d e f; g h i]')")
    K = np.array(values, float).reshape(3, 3)
    try:
        return intrinsics(K, name=f"K in {name}")
    except KitInputError as exc:
        raise KitInputError(str(exc)) from None


def read_calibration(path) -> np.ndarray:
    """Read the intrinsic matrix K from a P3 ``calibration.txt``.

    Accepts three rows of three numbers (WPI) or MATLAB syntax ``K = [a b c; d e f; g h i]``
    over one or several lines (UPenn), with CRLF or LF endings and with or without a final newline.

    Args:
        path: the calibration file (or a P3 folder, then ``calibration.txt`` inside it).

    Returns:
        ``(3, 3)`` float K in pixels.

    Raises:
        KitInputError: file missing, not 9 numbers, or not a valid K.

    Introduced in ``notebooks/01_fundamental_matrix.ipynb``.
    """
    p = file_in(path, "calibration.txt", "calibration file not found: {path} (a P3 folder needs calibration.txt with the 3x3 K)")
    return _parse_calibration_text(p.read_text(encoding="utf-8", errors="replace"), p.name)


# --------------------------------------------------------------------------------------------
# matching files


class UnionFind:
    """Disjoint sets of the nodes ``0 .. n-1`` (union-find with path compression).

    The root of a set is its smallest node, so sets come out in order of first appearance. With
    ``groups`` (one integer per node, e.g. its image), two sets that hold nodes of the same group
    are never joined: a track holds at most one feature per image.

    Used by the P3 reader (tracks are the connected components of the correspondences) and by
    :func:`course_lib.data.tracks.join_tracks` (verified matches, conflicting links refused).
    """

    def __init__(self, n: int = 0, groups=None):
        self.parent: list[int] = list(range(int(n)))
        self._groups = None if groups is None else [1 << int(g) for g in groups]  # bit mask per root

    def add(self, group: int | None = None) -> int:
        """A new node in a set of its own; returns its id."""
        self.parent.append(len(self.parent))
        if self._groups is not None:
            self._groups.append(1 << int(group))
        return len(self.parent) - 1

    def find(self, a: int) -> int:
        """The root of ``a``'s set."""
        p = self.parent
        root = a
        while p[root] != root:
            root = p[root]
        while p[a] != root:
            p[a], a = root, p[a]
        return root

    def union(self, a: int, b: int) -> bool:
        """Join the sets of ``a`` and ``b``; False (and nothing joined) if they share a group."""
        ra, rb = self.find(a), self.find(b)
        if ra == rb:
            return True
        if ra > rb:
            ra, rb = rb, ra
        if self._groups is not None:
            if self._groups[ra] & self._groups[rb]:
                return False
            self._groups[ra] |= self._groups[rb]
        self.parent[rb] = ra
        return True


def _parse_numbers(tokens: list[str], where: str) -> list[float]:
    """The tokens of one row as finite floats (the message names the first bad token)."""
    try:
        vals = [float(t) for t in tokens]
    except ValueError:
        bad = next(t for t in tokens if not _is_number(t))
        raise KitInputError(f"{where}: {bad!r} is not a number") from None
    if not all(map(math.isfinite, vals)):
        bad = next(t for t, x in zip(tokens, vals) if not math.isfinite(x))
        raise KitInputError(f"{where}: value {bad!r} is not finite (NaN or inf); fix or remove that row")
    return vals


def _is_number(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


def _parse_image_id(x: float, where: str, what: str) -> int:
    if x != int(x):
        raise KitInputError(f"{where}: {what} {x:g} is not an integer image id")
    return int(x)


def _find_image(folder: Path, image_id: int) -> str | None:
    for ext in IMAGE_EXTENSIONS:
        for cand in (f"{image_id}{ext}", f"{image_id}{ext.upper()}"):
            if (folder / cand).is_file():
                return cand
    return None


class _CorrespondenceGraph:
    """Features ``(image, u, v)`` as nodes, the unique correspondences of every pair as edges.

    What the P3 reader and :func:`tracks_from_pairs` build: equal pixels in one image are one
    feature; the components (a :class:`UnionFind` kept as edges arrive) become the tracks, with
    the inconsistency rule of the module docstring (:meth:`tracks`).
    """

    def __init__(self):
        self.uf = UnionFind()
        self.node_id: dict[tuple[int, float, float], int] = {}
        self.node_key: list[tuple[int, float, float]] = []
        self.pair_rows: dict[tuple[int, int], dict] = {}  # (i, j), i < j -> {(n_i, n_j): rgb} in insertion order
        self.n_correspondences = self.n_duplicates = 0

    def node(self, img: int, u: float, v: float) -> int:
        key = (img, u, v)
        n = self.node_id.get(key)
        if n is None:
            n = self.node_id[key] = self.uf.add()
            self.node_key.append(key)
        return n

    def add(self, i: int, ni: int, j: int, nj: int, rgb=None) -> None:
        """One correspondence between node ``ni`` of image ``i`` and node ``nj`` of image ``j``."""
        self.uf.union(ni, nj)
        self.n_correspondences += 1
        a, b, na, nb = (i, j, ni, nj) if i < j else (j, i, nj, ni)
        d = self.pair_rows.setdefault((a, b), {})
        if (na, nb) in d:
            self.n_duplicates += 1
        else:
            d[(na, nb)] = rgb

    def tracks(self, M: int) -> tuple[np.ndarray, np.ndarray, int, int]:
        """``track_uv (T, M, 2)``, ``node_track (n_nodes,)`` (-1: in no track), inconsistent components, dropped observations."""
        neighbours: dict[int, set[int]] = {}
        for d in self.pair_rows.values():
            for a, b in d:
                neighbours.setdefault(a, set()).add(b)
                neighbours.setdefault(b, set()).add(a)
        comps: dict[int, list[int]] = {}
        for n in range(len(self.node_key)):
            comps.setdefault(self.uf.find(n), []).append(n)
        tracks, n_conflict, n_dropped = [], 0, 0
        for root in sorted(comps):  # root = smallest node id = order of first appearance
            pieces, dropped = _consistent_pieces(comps[root], self.node_key, neighbours)
            tracks += [p for p in pieces if len(p) >= 2]
            n_conflict += dropped >= 0
            n_dropped += max(dropped, 0)
        node_track = np.full(len(self.node_key), -1, dtype=int)
        track_uv = np.full((len(tracks), M, 2), np.nan)
        for t, nodes in enumerate(tracks):
            node_track[nodes] = t
            for n in nodes:
                track_uv[t, self.node_key[n][0]] = self.node_key[n][1:]
        return track_uv, node_track, n_conflict, n_dropped

    def track_ids(self, node_track: np.ndarray, nodes: np.ndarray) -> np.ndarray:
        """``(N,)`` track of each correspondence ``nodes (N, 2)``, -1 where its features are not in one track."""
        t1, t2 = node_track[nodes[:, 0]], node_track[nodes[:, 1]]
        return np.where((t1 == t2) & (t1 >= 0), t1, -1)

    def pair_matches(self, node_track: np.ndarray) -> dict:
        """``{(i, j): PairMatches}`` of the unique correspondences, in sorted pair order."""
        matches = {}
        for (a, b) in sorted(self.pair_rows):
            d = self.pair_rows[(a, b)]
            ns = np.array(list(d.keys()), dtype=int).reshape(-1, 2)
            x1 = np.array([self.node_key[n][1:] for n in ns[:, 0]], float).reshape(-1, 2)
            x2 = np.array([self.node_key[n][1:] for n in ns[:, 1]], float).reshape(-1, 2)
            rgb = np.array(list(d.values()), np.uint8).reshape(-1, 3)
            matches[(a, b)] = PairMatches(x1, x2, rgb, self.track_ids(node_track, ns))
        return matches

    def track_colours(self, track_uv: np.ndarray, node_track: np.ndarray) -> np.ndarray:
        """``(T, 3)`` uint8: the colour of each track's feature in its first image, from its first row."""
        track_rgb = np.zeros((track_uv.shape[0], 3), np.uint8)
        rgb_set = np.zeros(track_uv.shape[0], bool)
        first_image = np.argmax(~np.isnan(track_uv[..., 0]), axis=1) if len(track_uv) else np.zeros(0, int)
        for d in self.pair_rows.values():
            for (na, _), rgb in d.items():
                t = node_track[na]
                if t >= 0 and not rgb_set[t] and self.node_key[na][0] == first_image[t]:
                    track_rgb[t], rgb_set[t] = rgb, True
        return track_rgb


def _consistent_pieces(members: list[int], node_key, neighbours) -> tuple[list[list[int]], int]:
    """The tracks of one connected component, by the inconsistency rule of the module docstring.

    Returns:
        The pieces (sorted node lists; those of one node are not tracks) and the number of
        dropped observations, -1 if the component was consistent (then it is the one piece).
    """
    per_image: dict[int, list[int]] = {}
    for n in members:
        per_image.setdefault(node_key[n][0], []).append(n)
    if all(len(ns) == 1 for ns in per_image.values()):
        return [members], -1
    # per image keep the feature with strictly the most correspondences, drop the rest (all on a tie)
    kept: set[int] = set()
    dropped = 0
    for ns in per_image.values():
        deg = sorted(((len(neighbours.get(n, ())), n) for n in ns), reverse=True)
        if len(ns) == 1 or deg[0][0] > deg[1][0]:
            kept.add(deg[0][1])
            dropped += len(ns) - 1
        else:
            dropped += len(ns)
    pieces = _connected_pieces(kept, neighbours)
    return pieces, dropped + sum(len(p) == 1 for p in pieces)


def _connected_pieces(kept: set[int], neighbours) -> list[list[int]]:
    """The connected pieces of the nodes ``kept`` (edges between kept nodes only), each sorted."""
    done: set[int] = set()
    pieces = []
    for start in sorted(kept):
        if start in done:
            continue
        piece, stack = [], [start]
        done.add(start)
        while stack:
            n = stack.pop()
            piece.append(n)
            for m in neighbours.get(n, ()):
                if m in kept and m not in done:
                    done.add(m)
                    stack.append(m)
        pieces.append(sorted(piece))
    return pieces


def tracks_from_pairs(n_images: int, pairs: dict) -> tuple[np.ndarray, dict, dict]:
    """Join pairwise correspondences into tracks (features are identified by equal pixels).

    The same union-find and inconsistency rule as :func:`read_p3` (module docstring).

    Args:
        n_images: M.
        pairs: ``{(i, j): (x1 (N, 2), x2 (N, 2))}`` with 0-based ``i != j``.

    Returns:
        ``track_uv (T, M, 2)`` (NaN where unseen), ``{(i, j): track_ids (N,)}`` (-1 where the
        correspondence is in no track) and a stats dict (``inconsistent_components``,
        ``dropped_observations``).
    """
    graph = _CorrespondenceGraph()
    pair_nodes = {}
    for (i, j), (x1, x2) in pairs.items():
        if not (0 <= i < n_images and 0 <= j < n_images) or i == j:
            raise KitInputError(f"pair ({i}, {j}) is not a pair of two different images among 0..{n_images - 1}")
        x1, x2 = np.asarray(x1, float).reshape(-1, 2), np.asarray(x2, float).reshape(-1, 2)
        ns = [(graph.node(int(i), float(a[0]), float(a[1])), graph.node(int(j), float(b[0]), float(b[1])))
              for a, b in zip(x1, x2)]
        for ni, nj in ns:
            graph.add(i, ni, j, nj)
        pair_nodes[(i, j)] = np.array(ns, int).reshape(-1, 2)
    track_uv, node_track, n_conf, n_drop = graph.tracks(n_images)
    ids = {key: graph.track_ids(node_track, ns) for key, ns in pair_nodes.items()}
    return track_uv, ids, {"inconsistent_components": n_conf, "dropped_observations": n_drop}


def _matching_files(folder: Path) -> list[tuple[int, Path]]:
    """``[(image id, matching{id}.txt)]`` in id order; the folder must exist and hold some."""
    if not folder.is_dir():
        raise KitInputError(f"P3 folder not found: {folder} (expected a folder with calibration.txt, matching1.txt, ... and 1.png, 2.png, ...)")
    files = []
    for p in folder.iterdir():
        m = _MATCHING_RE.match(p.name)
        if m and p.is_file():
            files.append((int(m.group(1)), p))
    files.sort()
    if not files:
        raise KitInputError(f"no matching*.txt files in {folder}: is this a P3 folder (calibration.txt, matching1.txt, ..., 1.png, ...)?")
    for file_id, path in files:
        if file_id < 1:
            raise KitInputError(f"{path.name}: image ids are 1-based, so there is no matching{file_id}.txt (rename it?)")
    return files


def _parse_row(s: str, where: str, file_id: int):
    """One row ``k R G B u v [j u_j v_j]*``: ``(rgb, u, v, [(j, u_j, v_j), ...])`` with 1-based ``j``."""
    vals = _parse_numbers(s.split(), where)
    k = _parse_image_id(vals[0], where, "the count k")
    if k < 1:
        raise KitInputError(f"{where}: k = {k}, but k counts the images the feature is seen in (including image {file_id}), so k >= 1")
    expected, found = 5 + 3 * (k - 1), len(vals) - 1
    if found != expected:
        why = "is the file truncated?" if found < expected else "are two rows merged, or is k wrong?"
        raise KitInputError(f"{where}: expected 5 + 3*(k-1) = {expected} numbers after k={k}, found {found} — {why}")
    rgb_f = vals[1:4]
    if any(c < 0 or c > 255 for c in rgb_f):
        raise KitInputError(f"{where}: colour {rgb_f} is outside 0..255")
    others = []
    for t in range(k - 1):
        jid = _parse_image_id(vals[6 + 3 * t], where, "image id")
        if jid < 1:
            raise KitInputError(f"{where}: image id {jid} out of range (ids are 1-based)")
        if jid == file_id:
            raise KitInputError(f"{where}: image id {jid} matches image {file_id} with itself")
        others.append((jid, vals[7 + 3 * t], vals[8 + 3 * t]))
    return tuple(int(round(c)) for c in rgb_f), vals[4], vals[5], others


def _read_matching_file(path: Path, file_id: int, graph: _CorrespondenceGraph) -> tuple[int, int]:
    """Add the rows of ``matching{file_id}.txt`` to ``graph``; returns (rows read, largest image id seen)."""
    i, n_rows, max_id = file_id - 1, 0, file_id
    text = path.read_text(encoding="utf-8", errors="replace")
    for lineno, line in enumerate(text.splitlines(), start=1):
        s = line.strip()
        if not s or _HEADER_RE.match(s):
            continue
        rgb, ui, vi, others = _parse_row(s, f"{path.name} line {lineno}", file_id)
        n_rows += 1
        ni = graph.node(i, ui, vi)
        for jid, uj, vj in others:
            max_id = max(max_id, jid)
            graph.add(i, ni, jid - 1, graph.node(jid - 1, uj, vj), rgb)
    return n_rows, max_id


def _image_names(folder: Path, max_id: int, require_images: bool) -> tuple[list[str], list[int]]:
    """Names of images ``1 .. M`` (M: the largest id in the matches or on disk) and the ids missing on disk."""
    n_files = 0
    while _find_image(folder, n_files + 1) is not None:
        n_files += 1
    names, missing = [], []
    for iid in range(1, max(max_id, n_files) + 1):
        nm = _find_image(folder, iid)
        if nm is None:
            missing.append(iid)
            nm = f"{iid}.png"
        names.append(nm)
    if require_images and missing:
        shown = ", ".join(f"{m}.png/.jpg" for m in missing[:6])
        raise KitInputError(
            f"{folder}: the matches refer to {len(names)} images but image file(s) {shown} are missing "
            "(copy the images next to the matching files, or call read_p3(folder, require_images=False) to read only the matches)"
        )
    return names, missing


def read_p3(folder, require_images: bool = True) -> P3Data:
    """Read a P3 folder: K, image names, unique pair matches and tracks.

    Args:
        folder: folder with ``calibration.txt``, ``matching*.txt`` and the images ``1.png`` (or
            ``.jpg``) ... ``M.png``.
        require_images: if True (default) every image referenced by the matches must exist
            (checked at once, read lazily by :meth:`P3Data.image`); set False to read only the
            matches (e.g. a folder written without images).

    Returns:
        :class:`P3Data` with 0-based image indices. Tracks with the inconsistency rule of this
        module's docstring; the counts in ``stats``.

    Raises:
        KitInputError: folder missing or without ``matching*.txt``, calibration missing or
            malformed, a malformed row (the message names the file and line), an image id out of
            range, a NaN value, or (with ``require_images``) missing image files.

    Introduced in ``notebooks/01_fundamental_matrix.ipynb``.
    """
    folder = Path(folder)
    files = _matching_files(folder)
    K = read_calibration(folder / "calibration.txt")
    graph = _CorrespondenceGraph()
    n_rows = max_id = 0
    for file_id, path in files:
        rows, top = _read_matching_file(path, file_id, graph)
        n_rows, max_id = n_rows + rows, max(max_id, top)
    names, missing = _image_names(folder, max_id, require_images)
    track_uv, node_track, n_conflict, n_dropped = graph.tracks(len(names))
    stats = {
        "rows": n_rows,
        "correspondences": graph.n_correspondences,
        "duplicate_correspondences": graph.n_duplicates,
        "unique_correspondences": graph.n_correspondences - graph.n_duplicates,
        "tracks": int(track_uv.shape[0]),
        "inconsistent_components": n_conflict,
        "dropped_observations": n_dropped,
        "missing_images": missing,
    }
    return P3Data(folder, names, K, track_uv, graph.track_colours(track_uv, node_track),
                  graph.pair_matches(node_track), stats, read_two_view_geometries(folder, len(names)), read_camera(folder),
                  read_source_names(folder, names))


def write_source_names(folder, image_names, source_names) -> Path:
    """Write :data:`SOURCE_NAMES_FILE`: the photos' own names beside their P3 names (``match`` does).

    Args:
        folder: the P3 folder. image_names: ``M`` P3 names (``1.png`` ...). source_names: ``M`` names of the photos.

    Returns:
        The file's path.
    """
    if len(image_names) != len(source_names):
        raise KitInputError(f"{len(image_names)} P3 names but {len(source_names)} source names: one per image")
    path = Path(folder) / SOURCE_NAMES_FILE
    path.write_text(json.dumps([{"p3_name": str(a), "source": str(b)} for a, b in zip(image_names, source_names)], indent=1))
    return path


def read_source_names(folder, image_names) -> list[str] | None:
    """The photos' own names of a P3 folder (:data:`SOURCE_NAMES_FILE`), in the order of ``image_names``; None without the file.

    Raises:
        KitInputError: a malformed file, or one that does not list exactly these images (the message says to delete it).
    """
    path = Path(folder) / SOURCE_NAMES_FILE
    if not path.is_file():
        return None
    fix = f"delete {path.name} to name the images by their P3 names, or run match again"
    try:
        rows = {str(r["p3_name"]): str(r["source"]) for r in json.loads(path.read_text())}
    except (ValueError, KeyError, TypeError) as exc:
        raise KitInputError(f"{path}: not a valid list of {{'p3_name', 'source'}} entries ({exc}); {fix}") from None
    missing = [n for n in image_names if n not in rows]
    if missing or len(rows) != len(image_names):
        raise KitInputError(f"{path} names {len(rows)} images but the folder has {len(image_names)}"
                            + (f" ({', '.join(missing[:3])} not among them)" if missing else "") + f": {fix}")
    names = [rows[n] for n in image_names]
    if len(set(names)) != len(names):
        raise KitInputError(f"{path}: two images have the same source name; {fix}")
    return names


# --------------------------------------------------------------------------------------------
# writer


def _fmt(x: float) -> str:
    return f"{x:.6f}"


def _matching_rows(track_uv: np.ndarray, rgb: np.ndarray) -> list[list[str]]:
    """The rows of each ``matching{i}.txt``: every track seen twice or more, from each of its images to the later ones."""
    seen = ~np.isnan(track_uv[..., 0])
    rows: list[list[str]] = [[] for _ in range(track_uv.shape[1])]
    for t in np.flatnonzero(seen.sum(1) >= 2):
        imgs = np.flatnonzero(seen[t])
        for a, i in enumerate(imgs[:-1]):
            later = imgs[a + 1:]
            parts = [str(len(later) + 1), *map(str, rgb[t]), _fmt(track_uv[t, i, 0]), _fmt(track_uv[t, i, 1])]
            for j in later:
                parts += [str(j + 1), _fmt(track_uv[t, j, 0]), _fmt(track_uv[t, j, 1])]
            rows[i].append(" ".join(parts) + " ")
    return rows


def _write_images(folder: Path, image_names: list[str], images) -> None:
    """Write the ``(H, W, 3)`` uint8 RGB ``images`` as ``folder/<name>`` (JPEG quality 90 or PNG)."""
    import cv2

    for name, img in zip(image_names, images):
        img = np.asarray(img)
        if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            raise KitInputError(f"image {name} has dtype {img.dtype} and shape {img.shape}: expected (H, W, 3) uint8 RGB")
        params = [cv2.IMWRITE_JPEG_QUALITY, 90] if name.lower().endswith((".jpg", ".jpeg")) else [cv2.IMWRITE_PNG_COMPRESSION, 1]
        if not cv2.imwrite(str(folder / name), np.ascontiguousarray(img[:, :, ::-1]), params):
            raise KitInputError(f"could not write image {folder / name}")


def write_p3(folder, image_names, K, track_uv, track_rgb, images=None) -> Path:
    """Write tracks as a P3 folder that :func:`read_p3` reads back.

    For every track and every image *i* in which it is seen with later images, ``matching{i+1}.txt``
    gets one row (as in the course files: a point seen in images 1, 2, 3 has a row with k = 3 in
    ``matching1.txt`` and one with k = 2 in ``matching2.txt``), so every pair of the track is listed.
    ``nFeatures`` is the number of rows, ids are 1-based, rows end with a trailing space, lines
    with LF. Coordinates are written with 6 decimals. Tracks seen in fewer than 2 images are skipped.
    :func:`read_p3` returns the tracks ordered by their first image (stable), so tracks given in
    that order come back in the same order.

    Args:
        folder: output folder (created if needed).
        image_names: ``M`` file names (e.g. ``["1.png", ..., "5.png"]``); they must be
            ``"{i+1}.png"`` / ``".jpg"`` for the folder to be a valid P3 folder.
        K: ``(3, 3)`` intrinsics, written to ``calibration.txt``.
        track_uv: ``(T, M, 2)`` pixels, NaN where unseen. Two different tracks must not share a
            pixel in the same image if they are to come back as written (the reader joins tracks
            by equal coordinates; :func:`course_lib.data.synthetic.write_scene_p3` uses that on
            purpose for wrong matches that are features of other points).
        track_rgb: ``(T, 3)`` uint8 colours.
        images: optional list of ``M`` ``(H, W, 3)`` uint8 RGB images, written under ``image_names``
            (the extension picks PNG or JPEG; JPEG quality 90; PNG at compression level 1: a 6 MP
            photo in about 0.2 s instead of 5 s at level 9, files about 10 % larger).

    Returns:
        The folder as a ``Path``.

    Introduced in ``notebooks/01_fundamental_matrix.ipynb``.
    """
    folder = Path(folder)
    K = intrinsics(K)
    image_names = [str(n) for n in image_names]
    M = len(image_names)
    track_uv = np.asarray(track_uv, dtype=float)
    if track_uv.ndim != 3 or track_uv.shape[1:] != (M, 2):
        raise KitInputError(f"track_uv has shape {track_uv.shape}: expected (T, {M}, 2) for {M} image names")
    track_rgb = np.asarray(track_rgb)
    if track_rgb.shape != (track_uv.shape[0], 3):
        raise KitInputError(f"track_rgb has shape {track_rgb.shape}: expected ({track_uv.shape[0]}, 3), one colour per track")
    if np.isnan(track_uv[..., 0]).__ne__(np.isnan(track_uv[..., 1])).any():
        raise KitInputError("track_uv has observations with only one of u, v NaN: mark unseen with NaN in both")
    if np.isinf(track_uv).any():
        raise KitInputError("track_uv contains inf: mark unseen observations with NaN")
    for i, n in enumerate(image_names):
        if Path(n).stem != str(i + 1):
            raise KitInputError(f"image_names[{i}] = {n!r}: P3 folders name image i {i + 1}.png or {i + 1}.jpg")
    if images is not None and len(images) != M:
        raise KitInputError(f"images has {len(images)} entries but there are {M} image names")
    rgb = np.clip(np.round(track_rgb.astype(float)), 0, 255).astype(int)

    folder.mkdir(parents=True, exist_ok=True)
    rows = _matching_rows(track_uv, rgb)
    for old in folder.glob("matching*.txt"):
        if _MATCHING_RE.match(old.name):
            old.unlink()
    for i in range(M - 1):
        with open(folder / f"matching{i + 1}.txt", "w", newline="\n") as f:
            f.write(f"nFeatures: {len(rows[i])}\n")
            for r in rows[i]:
                f.write(r + "\n")
    with open(folder / "calibration.txt", "w", newline="\n") as f:
        for r in K:
            f.write(" ".join(repr(float(x)) for x in r) + "\n")
    if images is not None:
        _write_images(folder, image_names, images)
    return folder
