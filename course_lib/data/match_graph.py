"""The correspondence graph: features ``(image, u, v)`` as nodes, matches as edges, tracks as its consistent components.

Equal pixels in one image are one feature; union-find (:class:`UnionFind`) joins the features that
matches link; a component with two different features of one image is cut by the P3 reader's
inconsistency rule (stated in :mod:`course_lib.data.p3`). The P3 reader
(:func:`course_lib.data.p3.read_p3`) and :func:`tracks_from_pairs` build their tracks this way;
:func:`course_lib.data.tracks.join_tracks` uses the same union-find.

Introduced in ``notebooks/01_fundamental_matrix.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from course_lib.validate import KitInputError

__all__ = ["PairMatches", "UnionFind", "CorrespondenceGraph", "tracks_from_pairs"]


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


class CorrespondenceGraph:
    """Features ``(image, u, v)`` as nodes, the unique correspondences of every pair as edges.

    What the P3 reader and :func:`tracks_from_pairs` build: equal pixels in one image are one
    feature; the components (a :class:`UnionFind` kept as edges arrive) become the tracks, with
    the inconsistency rule of :mod:`course_lib.data.p3` (:meth:`tracks`).
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
    """The tracks of one connected component, by the inconsistency rule of :mod:`course_lib.data.p3`.

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
    graph = CorrespondenceGraph()
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
