"""Tracks from *verified* matches: RANSAC on every image pair first, then join the inliers.

A track is one 3-D point seen in several images. Joining raw matches into tracks (as the P3
reader does for the file, :mod:`course_lib.data.p3`) lets a few wrong matches chain unrelated
points together: if feature A of image 1 is wrongly matched to feature B of image 3, which is
a real feature of another point, the two points' tracks become one, and a track with two
features in one image is useless. So the pipeline builds its tracks in two steps
(:func:`verified_pairs_and_tracks`, stage 1 of :func:`course_lib.sfm.pipeline.run_sfm`):

1. **Verify every pair** (:func:`verify_pairs`). A P3 folder written by ``match`` carries its
   verification (each verified pair's F, :mod:`course_lib.data.two_view`): F is refit on its
   matches within the threshold and those are the inliers (:func:`from_carried_geometry`), no
   second RANSAC. Other folders (the course's own matching files): RANSAC on F (notebook 01,
   :func:`ransac_every_pair`) with the normalized 8-point algorithm and the Sampson distance. In
   the instructor's kit that is the one RANSAC of :mod:`course_lib.sfm.fundamental`, with the
   random samples drawn and solved in batches (:func:`verify_pair`): one batched factorization
   for many 8-point problems instead of a Python loop over them; in the student kit, the
   student's own ``ransac_fundamental`` and ``sampson_distance`` (and ``eight_point`` for the
   refit of a carried F). Only the inlier matches go on.

   Photos matched by ``match`` get a **calibrated check** as well (:func:`check_calibrated`, after
   COLMAP's ``min_E_F_inlier_ratio``): F has two degrees of freedom more than the geometry of two
   calibrated cameras, and on look-alike texture (rows of bricks, windows and paving seen from
   different sides of a building) it fits dozens of wrong matches that slide along its epipolar
   lines. The five-point E with the camera's K fits far fewer of them: a pair whose E explains
   less than ``min_e_f_inlier_ratio`` of F's inliers gives no tracks, the others only the matches
   E explains (:func:`calibrated_check`). On a 16-photo ring of phone-like photos around the
   synthetic building, 71 of the 111 pairs ``match`` verified were such pairs (under 50 % of their
   matches right); their tracks joined the two sides of the building into one model 70 degrees wrong.
2. **Join the inliers** (:func:`course_lib.data.tracks.join_tracks`): features are nodes ``(image, u, v)`` (equal
   pixels are the same feature) and verified matches are edges. Edges are added by union-find
   (:class:`course_lib.data.p3.UnionFind`), the most trustworthy first (pairs with more inliers
   first, then by Sampson distance), and an edge that would put two different features of one image into one track is
   *refused*: the track is split at the conflicting link instead of being dropped whole.

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from course_lib.data.tracks import Tracks, join_tracks
from course_lib.exercises import call
from course_lib.sfm.initial_pair import five_point_essential, fundamental_from_essential, sampson_pixels
from course_lib.sfm.refit import refit_on_inliers
from course_lib.validate import KitInputError

try:  # the instructor's kit: notebook 01's RANSAC with batched samples and a preemptive test (faster)
    from course_lib.sfm.fundamental import eight_point_batch, ransac, sampson_distance_batch
except ImportError:  # the student kit: your ransac_fundamental, eight_point and sampson_distance of notebook 01
    eight_point_batch = ransac = sampson_distance_batch = None

__all__ = ["PairVerification", "Tracks", "verify_pair", "ransac_every_pair", "from_carried_geometry", "verify_pairs",
           "verified_pairs_and_tracks", "calibrated_check", "check_calibrated", "join_tracks", "verified_tracks"]


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


def verify_pair(x1: np.ndarray, x2: np.ndarray, rng: np.random.Generator, threshold_px: float = 1.0,
                confidence: float = 0.999, max_iters: int = 2000, batch: int = 256, bailout: int = 64) -> PairVerification:
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


def from_carried_geometry(x1: np.ndarray, x2: np.ndarray, F: np.ndarray, threshold_px: float) -> PairVerification:
    """A pair verified by ``match`` (its ``F`` carried in the P3 folder), without a RANSAC of its own.

    The last step of notebook 01's RANSAC (the refit on the inliers), from ``F`` instead of a sample's
    model: F is refit (8-point) on its matches within ``threshold_px`` (Sampson distance) while that
    set grows, and those are the inliers. The random sampling ran once, in ``match``
    (:mod:`course_lib.data.two_view`).

    Args:
        x1, x2: ``(N, 2)`` the pair's matches in the P3 folder. F: ``(3, 3)`` the carried F.
        threshold_px: inlier threshold on the Sampson distance (pixels).

    Returns:
        :class:`PairVerification` (``n_iters`` 0).
    """
    x1 = np.asarray(x1, float).reshape(-1, 2)
    x2 = np.asarray(x2, float).reshape(-1, 2)
    if len(x1) < 8:
        return PairVerification(None, np.zeros(len(x1), bool), np.full(len(x1), np.inf), 0,
                                f"{len(x1)} matches: the 8-point algorithm needs at least 8")
    F = np.asarray(F, float) / np.linalg.norm(F)
    if eight_point_batch is not None:
        model, d = refit_on_inliers(eight_point_batch, sampson_distance_batch, x1, x2, F, threshold_px, 8)
    else:
        model, d = refit_on_inliers(_eight_point_exercise, _sampson_exercise, x1, x2, F, threshold_px, 8)
    return PairVerification(model, d < threshold_px, d, 0)


def _eight_point_exercise(x1: np.ndarray, x2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The exercise ``eight_point`` as :func:`course_lib.sfm.refit.refit_on_inliers`' solver: one batch of one problem."""
    try:
        return np.asarray(call("eight_point", x1[0], x2[0]), float).reshape(1, 3, 3), np.ones(1, bool)
    except KitInputError:
        return np.zeros((1, 3, 3)), np.zeros(1, bool)


def _sampson_exercise(models: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """The exercise ``sampson_distance`` as :func:`course_lib.sfm.refit.refit_on_inliers`' error: ``(B, N)``."""
    return np.stack([np.asarray(call("sampson_distance", F, x1, x2), float).reshape(-1) for F in models])


def verify_pairs(data, rng: np.random.Generator, threshold_px: float = 1.0) -> tuple[dict, str]:
    """Stage 1 of SfM, the pair verification: ``({(i, j): PairVerification}, how)``.

    Where the P3 folder carries ``match``'s verification (``data.two_view``,
    :mod:`course_lib.data.two_view`), each verified pair is taken from it
    (:func:`from_carried_geometry`; pairs it did not verify stay unverified); otherwise RANSAC runs on
    every pair (:func:`ransac_every_pair`: the course's own matching files).

    Args:
        data: :class:`course_lib.data.p3.P3Data`. rng: seeded generator (RANSAC).
        threshold_px: inlier threshold on the Sampson distance (pixels).
    """
    carried = getattr(data, "two_view", None)
    if carried is None:
        return ransac_every_pair(data.matches, rng, threshold_px), "RANSAC on F"
    out = {}
    for key in sorted(data.matches):
        pm = data.matches[key]
        if key in carried:
            out[key] = from_carried_geometry(pm.x1, pm.x2, carried[key], threshold_px)
        else:
            out[key] = PairVerification(None, np.zeros(len(pm), bool), np.full(len(pm), np.inf), 0,
                                        "not verified by match (its matches come from tracks through other photos)")
    return out, "carried from match"


def calibrated_check(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, threshold_px: float, seed: int) -> tuple[np.ndarray, float]:
    """Which of a verified pair's inliers the calibrated geometry explains: ``(inliers (N,) bool, share)``.

    OpenCV's five-point essential matrix (``findEssentialMat``, USAC) on the pair's F-inliers with
    the camera's ``K``; a match is explained where its Sampson distance to ``F = K⁻ᵀ E K⁻¹`` is
    below ``threshold_px``. Right pairs keep nearly all of their F-inliers, pairs of look-alike
    texture far fewer (measured on rendered rings around the building).

    Args:
        x1, x2: ``(N, 2)`` the pair's F-inliers (pixels). K: ``(3, 3)``.
        threshold_px: Sampson distance (pixels). seed: OpenCV's RANSAC seed.

    Returns:
        The matches E explains and their share of the ``N`` (0 where no E is found or N < 5).
    """
    found = five_point_essential(x1, x2, K, threshold_px, seed) if len(x1) >= 5 else None
    if found is None:
        return np.zeros(len(x1), bool), 0.0
    inl = sampson_pixels(fundamental_from_essential(K, found[0]), x1, x2) < threshold_px
    return inl, float(inl.mean())


def check_calibrated(data, verifications: dict, rng: np.random.Generator, threshold_px: float, min_ratio: float,
                     K: np.ndarray | None = None) -> dict:
    """Every verified pair checked by :func:`calibrated_check` with the camera's K: a new ``{(i, j): PairVerification}``.

    A pair whose E explains less than ``min_ratio`` of its inliers loses its F (its ``note`` says
    why: it gives no tracks); the others keep only the inliers E explains.

    Args:
        data: :class:`course_lib.data.p3.P3Data` (``K``, ``matches``). verifications: ``{(i, j): PairVerification}``.
        rng: seeded generator (one RANSAC seed per verified pair, in sorted order).
        threshold_px: Sampson distance (pixels). min_ratio: the share E must explain.
        K: ``(3, 3)`` the camera's K (default ``data.K``; the self-calibrated one where the focal length was a guess).
    """
    K = np.asarray(data.K if K is None else K, float)
    keys = [k for k in sorted(verifications) if verifications[k].F is not None]
    seeds = dict(zip(keys, rng.integers(2**31 - 1, size=len(keys)).tolist()))
    out = dict(verifications)
    for key in keys:
        v, pm = verifications[key], data.matches[key]
        inl = np.flatnonzero(v.inliers)
        e_inl, share = calibrated_check(pm.x1[inl], pm.x2[inl], K, threshold_px, seeds[key])
        if share < min_ratio:
            out[key] = replace(v, F=None, inliers=np.zeros_like(v.inliers),
                               note=f"the five-point E explains {100 * share:.0f} % of F's {len(inl)} inliers (under "
                                    f"{100 * min_ratio:.0f} %): look-alike texture (repeated texture) that only F fits")
        else:
            keep = np.zeros_like(v.inliers)
            keep[inl[e_inl]] = True
            out[key] = replace(v, inliers=keep)
    return out


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


def verified_pairs_and_tracks(data, rng, threshold_px: float, min_matches: int, report: dict,
                              min_e_f_inlier_ratio: float = 0.0, calibrate=None):
    """Stage 1: every pair verified (``match``'s verification where the folder carries it, else RANSAC on F), then
    tracks from the inlier matches only (:func:`course_lib.sfm.tracks.verify_pairs`).

    Where the folder carries ``match``'s verification (photos) and ``min_e_f_inlier_ratio > 0``,
    each verified pair is checked with the calibrated geometry (:func:`course_lib.sfm.tracks.check_calibrated`):
    a pair whose five-point E explains less than that share of F's inliers is dropped (its row says
    why), the others keep the matches E explains. ``calibrate`` (a function of the verified pairs
    ``{(i, j): PairVerification}`` that returns the camera's ``(3, 3)`` K, e.g. the self-calibrated one of
    :mod:`course_lib.sfm.self_calibration`) gives the K of that check; default ``data.K``.

    Returns:
        ``pairs {(i, j): (F (3, 3), inliers (N,) bool)}`` of the pairs with at least ``min_matches``
        inliers, and the :class:`~course_lib.sfm.tracks.Tracks`; ``report`` gets ``pairs`` and ``tracks``.
    """
    ver, how = verify_pairs(data, rng, threshold_px)
    K = calibrate(ver) if calibrate is not None else None
    if min_e_f_inlier_ratio > 0 and getattr(data, "two_view", None) is not None:
        ver = check_calibrated(data, ver, rng, threshold_px, min_e_f_inlier_ratio, K)
        how += f", checked by the five-point E (at least {min_e_f_inlier_ratio:g} of F's inliers)"
    report["verification"] = how
    pairs, rows = {}, []
    for (i, j), v in ver.items():
        row = {"pair": [i, j], "names": [data.image_names[i], data.image_names[j]], "matches": len(v.inliers),
               "inliers": v.n_inliers, "ransac_iterations": int(v.n_iters)}
        if v.F is None or v.n_inliers < min_matches:
            row["note"] = v.note or f"{v.n_inliers} inliers: too few to trust F"
        else:
            pairs[(i, j)] = (v.F, v.inliers)
        rows.append(row)
    tracks = verified_tracks(data, ver, min_inliers=min_matches)
    report["pairs"] = rows
    report["tracks"] = {"raw_tracks": int(data.n_tracks) if hasattr(data, "n_tracks") else None,
                        "raw_observations": int(np.isfinite(np.asarray(data.track_uv, float)[..., 0]).sum()),
                        "verified_tracks": tracks.stats["tracks"],
                        "verified_observations": int(np.isfinite(tracks.uv[..., 0]).sum()),
                        "verified_matches": tracks.stats["edges"],
                        "refused_links": tracks.stats["refused_edges"]}
    return pairs, tracks
