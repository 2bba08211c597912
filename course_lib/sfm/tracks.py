"""Tracks from *verified* matches: RANSAC on every image pair first, then join the inliers.

A track is one 3-D point seen in several images. Joining raw matches into tracks (as the P3
reader does for the file, :mod:`course_lib.data.p3`) lets a few wrong matches chain unrelated
points together: if feature A of image 1 is wrongly matched to feature B of image 3, which is
a real feature of another point, the two points' tracks become one, and a track with two
features in one image is useless. So the pipeline builds its tracks in two steps:

1. **Verify every pair** (notebook 01, :func:`ransac_every_pair`): RANSAC on F with the
   normalized 8-point algorithm and the Sampson distance. In the instructor's kit that is the one
   RANSAC of :mod:`course_lib.sfm.fundamental`, with the random samples drawn and solved in
   batches (:func:`verify_pair`): one batched factorization for many 8-point problems instead of
   a Python loop over them; in the student kit, the student's own ``ransac_fundamental`` and
   ``sampson_distance``. Only the inlier matches go on.
2. **Join the inliers** (:func:`join_tracks`): features are nodes ``(image, u, v)`` (equal
   pixels are the same feature) and verified matches are edges. Edges are added by union-find
   (:class:`course_lib.data.p3.UnionFind`), the most trustworthy first (pairs with more inliers
   first, then by Sampson distance), and an edge that would put two different features of one image into one track is
   *refused*: the track is split at the conflicting link instead of being dropped whole.

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from course_lib.data.p3 import UnionFind
from course_lib.exercises import call
from course_lib.validate import KitInputError

try:  # the instructor's kit: notebook 01's RANSAC with batched samples and a preemptive test (faster)
    from course_lib.sfm.fundamental import ransac
except ImportError:  # the student kit: your ransac_fundamental and sampson_distance of notebook 01
    ransac = None

__all__ = ["PairVerification", "Tracks", "verify_pair", "ransac_every_pair", "join_tracks", "verified_tracks"]


@dataclass
class PairVerification:
    """RANSAC on F for one image pair.

    Attributes:
        F: ``(3, 3)`` fundamental matrix (``x2ᵀ F x1 = 0``), None if the pair was not verified.
        inliers: ``(N,)`` bool, the matches that agree with F.
        sampson: ``(N,)`` Sampson distance of every match to F, pixels (inf if no F).
        n_iters: RANSAC samples drawn.
        note: why the pair was not verified ("" if it was).
    """

    F: np.ndarray | None
    inliers: np.ndarray
    sampson: np.ndarray
    n_iters: int
    note: str = ""

    @property
    def n_inliers(self) -> int:
        return int(self.inliers.sum())


def verify_pair(
    x1: np.ndarray,
    x2: np.ndarray,
    rng: np.random.Generator,
    threshold_px: float = 1.0,
    confidence: float = 0.999,
    max_iters: int = 2000,
    batch: int = 256,
    bailout: int = 64,
) -> PairVerification:
    """RANSAC on F (8-point samples, Sampson distance, adaptive stop), samples solved in batches.

    The RANSAC of notebook 01 (in the instructor's kit), :func:`course_lib.sfm.fundamental.ransac` with the batched
    8-point solver and Sampson distance: draw 8 matches, fit F, count the matches within
    ``threshold_px``, stop after ``log(1 - confidence) / log(1 - w⁸)`` samples for the best
    inlier ratio ``w``; then refit F on the inliers while the inlier set grows. Here ``batch``
    samples are drawn and solved at once. In the student kit (no reference RANSAC) the student's
    own ``ransac_fundamental`` and ``sampson_distance`` of notebook 01 verify the pair, called as
    their stubs document (``batch`` and ``bailout`` are not used there).

    Args:
        x1, x2: ``(N, 2)`` matching pixels of the two images.
        rng: seeded ``numpy.random.Generator``.
        threshold_px: inlier threshold on the Sampson distance (pixels).
        confidence: desired probability of one outlier-free sample.
        max_iters: the most samples.
        batch: samples solved per batched call.
        bailout: size of the preemptive test of :func:`~course_lib.sfm.fundamental.ransac` (0: off).

    Returns:
        :class:`PairVerification` (``note`` says why not, where fewer than 8 matches or only
        degenerate samples).
    """
    x1 = np.asarray(x1, float).reshape(-1, 2)
    x2 = np.asarray(x2, float).reshape(-1, 2)
    n = len(x1)
    if len(x2) != n:
        raise KitInputError(f"x1 has {n} rows but x2 has {len(x2)}: the matches must be paired row by row")
    none = PairVerification(None, np.zeros(n, bool), np.full(n, np.inf), 0)
    if n < 8:
        none.note = f"{n} matches: the 8-point algorithm needs at least 8"
        return none
    if ransac is None:
        return _verify_with_exercises(x1, x2, rng, threshold_px, confidence, max_iters, none)
    res = ransac(x1, x2, rng, threshold=threshold_px, confidence=confidence, max_iters=max_iters, batch=batch,
                 bailout=bailout)
    if res is None:
        none.n_iters, none.note = max_iters, "only degenerate 8-point samples (all matches on a line or repeated?)"
        return none
    return PairVerification(res.F, res.inliers, res.distances, res.n_iters)


def _verify_with_exercises(x1, x2, rng, threshold_px, confidence, max_iters, none: PairVerification) -> PairVerification:
    """:func:`verify_pair` by the exercises ``ransac_fundamental`` and ``sampson_distance`` (the student kit)."""
    try:
        res = call("ransac_fundamental", x1, x2, rng, threshold_px, confidence, max_iters)
    except NotImplementedError:
        raise  # the stand-in: it names the notebook to finish
    except Exception as exc:  # noqa: BLE001 - a pair your RANSAC cannot verify (few or bad matches) is left out
        none.n_iters = max_iters
        none.note = f"your ransac_fundamental raised {type(exc).__name__} on these {len(x1)} matches: {str(exc)[:200]}"
        return none
    F = np.asarray(res.F, float)
    inliers = np.asarray(res.inliers, bool).reshape(-1)
    if F.shape != (3, 3) or inliers.shape != (len(x1),):
        raise KitInputError(f"ransac_fundamental returned F {F.shape} and inliers {inliers.shape}: expected (3, 3) and "
                            f"({len(x1)},) (see its docstring)")
    d = np.asarray(call("sampson_distance", F, x1, x2), float).reshape(-1)
    return PairVerification(F, inliers, d, int(res.n_iters))


def ransac_every_pair(matches: dict, rng: np.random.Generator, threshold_px: float = 1.0, **kw) -> dict:
    """:func:`verify_pair` for every pair of a P3 ``matches`` dict ``{(i, j): PairMatches}``, in sorted order.

    Returns:
        ``{(i, j): PairVerification}``.
    """
    return {key: verify_pair(matches[key].x1, matches[key].x2, rng, threshold_px, **kw) for key in sorted(matches)}


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


def verified_tracks(data, verifications: dict, min_inliers: int = 8) -> Tracks:
    """Tracks of a P3 data set from its verified pairs, trusted pairs first.

    Args:
        data: :class:`course_lib.data.p3.P3Data` (its ``matches``).
        verifications: ``{(i, j): PairVerification}`` from :func:`ransac_every_pair`.
        min_inliers: pairs with fewer inliers contribute no edges (too few to trust their F).

    Returns:
        :class:`Tracks`; ``stats['pairs_used']`` counts the pairs that gave edges.
    """
    edges = []
    order = sorted(verifications, key=lambda k: (-verifications[k].n_inliers, k))
    used = 0
    for key in order:
        v = verifications[key]
        if v.F is None or v.n_inliers < min_inliers:
            continue
        used += 1
        pm = data.matches[key]
        inl = np.flatnonzero(v.inliers)
        inl = inl[np.argsort(v.sampson[inl], kind="stable")]  # best matches first
        edges.append((key[0], key[1], pm.x1[inl], pm.x2[inl], pm.rgb[inl]))
    tr = join_tracks(len(data.image_names), edges)
    tr.stats["pairs_used"] = used
    return tr
