"""Pairwise matches joined into tracks, the most trusted first, refusing links that would break a track.

A track is one 3-D point seen in several images: at most one feature per image. Joining matches
naively (connected components) lets one wrong match chain two points together, and a component
with two features of one image must then be dropped whole (the P3 reader's rule,
:func:`course_lib.data.p3.tracks_from_pairs`). :func:`join_tracks` instead adds the matches one by
one, the most trustworthy first (the caller's order: pairs with more inliers, then the matches
nearest their epipolar line), with union-find (:class:`course_lib.data.p3.UnionFind`), and
*refuses* a link that would put two different features of one image into one track: the track is
split at the conflicting link instead of being dropped.

``match`` writes its tracks this way (:mod:`course_lib.data.cli_match`), and ``sfm`` joins its
verified tracks this way (:func:`course_lib.sfm.tracks.verified_tracks`).

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from course_lib.data.features import RATIO, detect_and_match, track_colours
from course_lib.data.p3 import UnionFind, tracks_from_pairs
from course_lib.validate import KitInputError

__all__ = ["Tracks", "join_tracks", "tracks_from_images"]


@dataclass
class Tracks:
    """Tracks joined from verified matches.

    Attributes:
        uv: ``(T, M, 2)`` pixels of each track in each image, NaN where unseen.
        rgb: ``(T, 3)`` uint8 colour (of the feature in the lower-numbered image of its first edge).
        stats: ``edges`` (verified matches used), ``refused_edges`` (links refused because they
            would put two features of one image into one track), ``tracks``.
    """

    uv: np.ndarray
    rgb: np.ndarray
    stats: dict = field(default_factory=dict)


def join_tracks(n_images: int, edges: list) -> Tracks:
    """Union-find over verified matches; a link that joins two features of one image is refused.

    Args:
        n_images: M.
        edges: list of ``(i, j, x1 (N, 2), x2 (N, 2), rgb (N, 3) or None)`` verified matches
            between images ``i != j``, **in order of trust** (the first are joined first).
            Features are identified by equal pixels within an image.

    Returns:
        :class:`Tracks` with every track of two or more features.
    """
    M = int(n_images)
    # one node per distinct (image, u, v): np.unique over each image's endpoints of all edges
    ends = [[] for _ in range(M)]  # per image: (edge number, side, pixels)
    for e, (i, j, x1, x2, _) in enumerate(edges):
        if not (0 <= i < M and 0 <= j < M) or i == j:
            raise KitInputError(f"pair ({i}, {j}) is not a pair of two different images among 0..{M - 1}")
        ends[i].append((e, 0, np.asarray(x1, float).reshape(-1, 2)))
        ends[j].append((e, 1, np.asarray(x2, float).reshape(-1, 2)))
    node_of = [[None, None] for _ in edges]  # node ids of both ends of every edge list
    node_img, node_uv, n_nodes = [], [], 0
    for i in range(M):
        if not ends[i]:
            continue
        u, inv = np.unique(np.concatenate([x for _, _, x in ends[i]]), axis=0, return_inverse=True)
        inv = inv.ravel() + n_nodes
        start = 0
        for e, side, x in ends[i]:
            node_of[e][side] = inv[start:start + len(x)]
            start += len(x)
        node_img.append(np.full(len(u), i))
        node_uv.append(u)
        n_nodes += len(u)
    node_img = np.concatenate(node_img) if node_img else np.zeros(0, int)
    node_uv = np.concatenate(node_uv) if node_uv else np.zeros((0, 2))

    node_rgb = np.zeros((n_nodes, 3), np.uint8)
    has_rgb = np.zeros(n_nodes, bool)
    for e, (i, j, x1, x2, rgb) in enumerate(edges):
        a = node_of[e][0]
        if rgb is not None and len(a):
            new = ~has_rgb[a]
            node_rgb[a[new]] = np.asarray(rgb, np.uint8).reshape(-1, 3)[new]
            has_rgb[a[new]] = True
    A = np.concatenate([n[0] for n in node_of]) if edges else np.zeros(0, int)
    Bn = np.concatenate([n[1] for n in node_of]) if edges else np.zeros(0, int)
    # a track holds one feature per image: a link between two tracks that share an image is refused
    uf = UnionFind(n_nodes, groups=node_img)
    refused = sum(not uf.union(a, b) for a, b in zip(A.tolist(), Bn.tolist()))
    roots = np.array([uf.find(x) for x in range(n_nodes)], dtype=int)
    linked = np.zeros(n_nodes, bool)
    linked[A] = linked[Bn] = True
    _, track_of, sizes = np.unique(roots, return_inverse=True, return_counts=True)
    keep_track = sizes >= 2
    new_id = np.cumsum(keep_track) - 1
    T = int(keep_track.sum())
    uv = np.full((T, M, 2), np.nan)
    rgb = np.zeros((T, 3), np.uint8)
    sel = keep_track[track_of] & linked
    t_of = new_id[track_of[sel]]
    uv[t_of, node_img[sel]] = node_uv[sel]
    # colour: of the first node (lowest id = lowest image) that has one
    for n in np.flatnonzero(sel)[::-1]:
        if has_rgb[n]:
            rgb[new_id[track_of[n]]] = node_rgb[n]
    return Tracks(uv, rgb, {"edges": int(len(A)), "refused_edges": refused, "tracks": T})


def tracks_from_images(images: list[np.ndarray], ratio: float = RATIO):
    """SIFT matches of all pairs joined into tracks, with each track's colour.

    Args:
        images: M ``(H, W, 3)`` uint8 RGB images.
        ratio: Lowe's ratio.

    Returns:
        ``track_uv (T, M, 2)``, ``track_rgb (T, 3)`` uint8 (colour at the first observation),
        ``pairs`` (the raw matches of :func:`detect_and_match`) and the stats of
        :func:`course_lib.data.p3.tracks_from_pairs`.
    """
    pairs = detect_and_match(images, ratio)
    track_uv, _, tstats = tracks_from_pairs(len(images), pairs)
    return track_uv, track_colours(track_uv, images), pairs, tstats
