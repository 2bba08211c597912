"""Incremental Structure from Motion on a P3 folder: the notebooks 01-05 chained into one pipeline.

:func:`run_sfm` takes the matches of a P3 folder (:func:`course_lib.data.p3.read_p3`) and returns a
:class:`Reconstruction` (poses of the registered images, 3-D points, inlier observations) and a
report of every stage. The stages are the notebooks' exercises, called from the reference
library:

1. **Verified tracks** (notebook 01, :mod:`course_lib.sfm.tracks`): RANSAC on F for every image
   pair (the 8-point algorithm and the Sampson distance of
   :func:`~course_lib.sfm.fundamental.ransac_fundamental`, samples solved in batches), then the
   tracks are joined from the *inlier* matches only, by union-find, trusted pairs first; a link
   that would put two features of one image into one track is refused, so the track is split
   there instead of being dropped. (The P3 reader's tracks, joined from the raw matches, are
   not used: a few wrong matches that are real features of other points chain unrelated tracks.)
2. **Initial pair** (notebooks 02, 03): among the pairs with many inliers, the one whose
   triangulated points have the widest triangulation angles (a long baseline): score =
   number of inlier points triangulated in front of both cameras with an angle above
   ``init_min_angle_deg``. E from F (:func:`~course_lib.sfm.essential.essential_from_fundamental`),
   the four candidates and the cheirality test (:func:`~course_lib.sfm.triangulation.choose_pose`)
   give the second camera; the first is the world frame (``R = I, t = 0``) and the baseline has
   length 1 (the unit of the reconstruction).
3. **Triangulation** (notebook 03): linear from two views (the new image and its farthest
   registered partner), then non-linear over all registered views that see the track (skipped
   for images after the initial pair when bundle adjustment follows at once, since BA refines the
   new points with everything else); a point is kept if it lies in front of those cameras,
   reprojects within ``max_reproj_px`` and its triangulation angle is at least ``min_angle_deg``;
   observations that reproject badly are rejected.
4. **Registration** (notebook 04): the unregistered image that sees the most triangulated tracks
   next: PnP RANSAC (:func:`~course_lib.sfm.pnp.pnp_ransac`) then non-linear PnP on the inliers.
   This is how UPenn images 5 and 6, which share no matches with images 1 and 2, come in.
5. **Bundle adjustment** (notebook 05, :func:`~course_lib.sfm.bundle_adjustment.bundle_adjust`):
   after every registration (robust Huber loss, then observations beyond ``max_reproj_px`` are
   removed); at the end, tracks that failed earlier are triangulated again and rejected
   observations that now fit are used again (:func:`_retriangulate_and_complete`), the noise
   level ``sigma`` is estimated from the median reprojection
   error, observations beyond ``4 sigma`` (within [1, 4] px) are removed and a final BA polishes
   the result: plain least squares where the errors look Gaussian, a Cauchy loss at ``2 sigma``
   (at least 0.3 px) where they have a heavy tail (SIFT). Points seen in only two images cannot
   reveal a wrong match, so the cameras are refined first with the points seen three or more
   times, and the two-view points after them.

P3 data quirks handled upstream by the reader (:mod:`course_lib.data.p3`): duplicate rows are
merged, features are identified by equal coordinates. Matches contain outliers on purpose
(step 1). ``Reconstruction.track_uv`` holds the verified tracks (not ``P3Data.track_uv``).

Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from course_lib.conventions import camera_center, projection_matrix
from course_lib.sfm.bundle_adjustment import bundle_adjust, reprojection_error_stats
from course_lib.threads import single_threaded_blas
from course_lib.validate import KitInputError, intrinsics

__all__ = ["Reconstruction", "run_sfm", "triangulation_angles_deg", "reprojection_error_matrix"]


@dataclass
class Reconstruction:
    """The result of :func:`run_sfm`.

    Attributes:
        K: ``(3, 3)`` intrinsics.
        image_names: M file names.
        image_size: ``(W, H)``.
        registered: ``(M,)`` bool, images with a pose.
        R_cw: ``(M, 3, 3)`` rotations, NaN for unregistered images.
        t_cw: ``(M, 3)`` translations, NaN for unregistered images.
        X: ``(T, 3)`` one point per track, NaN where the track was not triangulated.
        rgb: ``(T, 3)`` uint8 colour of each track.
        track_uv: ``(T, M, 2)`` all observations of the verified tracks
            (:mod:`course_lib.sfm.tracks`, not the reader's ``P3Data.track_uv``), NaN where unseen.
        inlier: ``(T, M)`` bool, the observations the reconstruction uses (registered image,
            triangulated point, not rejected as an outlier).
        report: per-stage numbers (see :func:`run_sfm`), JSON-serializable.
    """

    K: np.ndarray
    image_names: list[str]
    image_size: tuple[int, int]
    registered: np.ndarray
    R_cw: np.ndarray
    t_cw: np.ndarray
    X: np.ndarray
    rgb: np.ndarray
    track_uv: np.ndarray
    inlier: np.ndarray
    report: dict = field(default_factory=dict)

    @property
    def n_points(self) -> int:
        """Number of triangulated points."""
        return int(np.isfinite(self.X).all(axis=1).sum())

    @property
    def n_registered(self) -> int:
        return int(self.registered.sum())

    @property
    def observations(self) -> np.ndarray:
        """``(T, M, 2)`` pixels of the inlier observations, NaN elsewhere (the input of BA)."""
        return np.where(self.inlier[..., None], self.track_uv, np.nan)

    @property
    def centers(self) -> np.ndarray:
        """``(M, 3)`` camera centres, NaN for unregistered images."""
        C = np.full((len(self.image_names), 3), np.nan)
        for i in np.flatnonzero(self.registered):
            C[i] = camera_center(self.R_cw[i], self.t_cw[i])
        return C

    def reprojection_errors(self) -> np.ndarray:
        """``(T, M)`` reprojection error of each inlier observation in pixels, NaN elsewhere."""
        return reprojection_error_matrix(self.K, self.R_cw, self.t_cw, self.X, self.observations)

    def error_stats(self) -> dict[str, float]:
        """rms / mean / median / max reprojection error over the inlier observations (pixels)."""
        e = self.reprojection_errors()
        return reprojection_error_stats(e[np.isfinite(e)])

    def cameras(self) -> list[tuple]:
        """``[(R_cw, t_cw, K, (W, H), name), ...]`` of the registered images (for :mod:`course_lib.viz`)."""
        return [
            (self.R_cw[i], self.t_cw[i], self.K, self.image_size, self.image_names[i]) for i in np.flatnonzero(self.registered)
        ]

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """``(X (P, 3), rgb (P, 3))`` of the triangulated points."""
        ok = np.isfinite(self.X).all(axis=1)
        return self.X[ok], self.rgb[ok]

    def write_colmap(self, folder) -> Path:
        """Write the model as COLMAP text files (:func:`course_lib.data.colmap.write_colmap_text`)."""
        from course_lib.data.colmap import write_colmap_text

        return write_colmap_text(
            folder, self.K, self.image_size, self.image_names, self.R_cw, self.t_cw, self.registered, self.X, self.rgb,
            self.observations,
        )


# ---------------------------------------------------------------------------------------------
# Small geometric helpers
# ---------------------------------------------------------------------------------------------


def reprojection_error_matrix(K, R_cw, t_cw, X, uv) -> np.ndarray:
    """``(T, M)`` reprojection errors (pixels) of the finite observations ``uv (T, M, 2)``, NaN elsewhere.

    Observations behind the camera get ``inf``.
    """
    K = np.asarray(K, float)
    T, M = uv.shape[:2]
    E = np.full((T, M), np.nan)
    seen = np.isfinite(uv).all(axis=2) & np.isfinite(X).all(axis=1)[:, None]
    for i in range(M):
        j = np.flatnonzero(seen[:, i])
        if len(j) == 0 or not np.isfinite(R_cw[i]).all():
            continue
        xc = X[j] @ R_cw[i].T + t_cw[i]
        xh = xc @ K.T
        with np.errstate(divide="ignore", invalid="ignore"):
            e = np.linalg.norm(xh[:, :2] / xh[:, 2:3] - uv[j, i], axis=1)
        e[~(xc[:, 2] > 0)] = np.inf
        E[j, i] = e
    return E


def triangulation_angles_deg(X: np.ndarray, centers: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``(T,)`` the largest angle (degrees) between the rays from the observing cameras to each point.

    Args:
        X: ``(T, 3)`` points. centers: ``(M, 3)`` camera centres. mask: ``(T, M)`` which cameras see
            each point. Points seen by fewer than two cameras get 0.
    """
    T, M = mask.shape
    rays = np.full((T, M, 3), np.nan)
    for i in range(M):
        if mask[:, i].any():
            d = X - centers[i]
            with np.errstate(divide="ignore", invalid="ignore"):
                rays[:, i] = d / np.linalg.norm(d, axis=1, keepdims=True)
    best = np.zeros(T)
    for a in range(M):
        for b in range(a + 1, M):
            both = mask[:, a] & mask[:, b]
            if both.any():
                c = np.clip(np.einsum("ij,ij->i", rays[both, a], rays[both, b]), -1.0, 1.0)
                best[both] = np.maximum(best[both], np.degrees(np.arccos(c)))
    return best


def _stats(E: np.ndarray) -> dict[str, float]:
    e = E[np.isfinite(E)]
    s = reprojection_error_stats(e)
    return {k: round(v, 4) for k, v in s.items()}


def _image_size(data) -> tuple[int, int]:
    try:
        return tuple(int(v) for v in data.image_size)
    except (KitInputError, FileNotFoundError, OSError, AttributeError):
        uv = data.track_uv
        return (int(np.ceil(np.nanmax(uv[..., 0]) + 1)), int(np.ceil(np.nanmax(uv[..., 1]) + 1)))


# ---------------------------------------------------------------------------------------------
# The pipeline
# ---------------------------------------------------------------------------------------------


class _State:
    """Arrays the stages share (all indexed by track j and image i)."""

    def __init__(self, track_uv, K):
        self.K = K
        self.uv = np.asarray(track_uv, float)
        T, M = self.uv.shape[:2]
        self.T, self.M = T, M
        self.visible = np.isfinite(self.uv).all(axis=2)
        self.candidate = self.visible.copy()  # observation not (yet) rejected
        self.registered = np.zeros(M, dtype=bool)
        self.R = np.full((M, 3, 3), np.nan)
        self.t = np.full((M, 3), np.nan)
        self.X = np.full((T, 3), np.nan)

    @property
    def has_X(self) -> np.ndarray:
        return np.isfinite(self.X).all(axis=1)

    @property
    def inlier(self) -> np.ndarray:
        return self.candidate & self.registered[None, :] & self.has_X[:, None]

    def centers(self) -> np.ndarray:
        C = np.full((self.M, 3), np.nan)
        for i in np.flatnonzero(self.registered):
            C[i] = camera_center(self.R[i], self.t[i])
        return C

    def errors(self) -> np.ndarray:
        return reprojection_error_matrix(self.K, self.R, self.t, self.X, np.where(self.inlier[..., None], self.uv, np.nan))

    def observation_stats(self) -> dict[str, float]:
        return _stats(self.errors())


def _verified_tracks(data, rng, threshold_px: float, min_matches: int, report: dict):
    """RANSAC on F for every pair, then tracks from the inlier matches only (:mod:`course_lib.sfm.tracks`)."""
    from course_lib.sfm.tracks import ransac_every_pair, verified_tracks

    ver = ransac_every_pair(data.matches, rng, threshold_px)
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


def _two_view(data, st: _State, i: int, j: int, F: np.ndarray, inl: np.ndarray):
    """Relative pose of the pair from F and the triangulated inlier matches (camera i at the origin)."""
    from course_lib.sfm.essential import essential_from_fundamental, pose_candidates
    from course_lib.sfm.triangulation import choose_pose

    pm = data.matches[(i, j)]
    x1, x2 = pm.x1[inl], pm.x2[inl]
    E = essential_from_fundamental(F, st.K)
    R4, C4 = pose_candidates(E)
    choice = choose_pose(R4, C4, st.K, x1, x2)
    C2 = camera_center(choice.R_cw, choice.t_cw)
    a = choice.X
    r1 = a / np.linalg.norm(a, axis=1, keepdims=True)
    r2 = (a - C2) / np.linalg.norm(a - C2, axis=1, keepdims=True)
    ang = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", r1, r2), -1, 1)))
    return choice, ang


#: A pair whose F inliers a homography explains this well is degenerate for a two-view start.
H_INLIER_RATIO = 0.8
#: How many pairs (those with the most inliers) are scored as the initial pair.
MAX_INITIAL_CANDIDATES = 20


def pair_degeneracy(x1: np.ndarray, x2: np.ndarray, K: np.ndarray, threshold_px: float) -> tuple[str, float]:
    """Is a pair's geometry a homography (pure rotation or a planar scene), where F and E are ill-defined?

    A homography ``H`` (OpenCV's RANSAC, ``threshold_px``) is fitted to the pair's F inliers. If it
    explains more than :data:`H_INLIER_RATIO` of them, the pair cannot start a reconstruction:
    if ``K⁻¹ H K`` is a rotation (equal singular values), the camera only turned (no baseline,
    nothing to triangulate), otherwise the points lie on a plane (F is not unique).

    Args:
        x1, x2: ``(N, 2)`` inlier matches. K: ``(3, 3)``. threshold_px: pixels.

    Returns:
        ``(kind, ratio)``: kind ``""`` (fine), ``"pure rotation"`` or ``"planar"``; the share of the
        matches the homography explains.
    """
    import cv2

    if len(x1) < 8:
        return "", 0.0
    # 200 samples of 4 find a homography that explains 80 % of the matches with certainty
    # (1 - 0.8^4)^200 < 1e-40; OpenCV's default of 2000 costs 10x more on the pairs where none does
    H, mask = cv2.findHomography(x1.astype(np.float64), x2.astype(np.float64), cv2.RANSAC, threshold_px,
                                 maxIters=200, confidence=0.999)
    if H is None:
        return "", 0.0
    ratio = float(mask.ravel().astype(bool).mean())
    if ratio <= H_INLIER_RATIO:
        return "", ratio
    s = np.linalg.svd(np.linalg.inv(K) @ H @ K, compute_uv=False)
    return ("pure rotation" if s[0] / s[2] < 1.02 else "planar"), ratio


def _choose_initial_pair(data, st: _State, pairs: dict, min_inliers: int, min_angle_deg: float, threshold_px: float,
                         report: dict):
    scored, degenerate = [], []
    # the MAX_INITIAL_CANDIDATES pairs with the most inliers are candidates (as COLMAP tries them)
    ranked = sorted(pairs, key=lambda k: (-int(pairs[k][1].sum()), k))[:MAX_INITIAL_CANDIDATES]
    for (i, j) in ranked:
        F, inl = pairs[(i, j)]
        n = int(inl.sum())
        if n < min_inliers:
            continue
        pm = data.matches[(i, j)]
        kind, ratio = pair_degeneracy(pm.x1[inl], pm.x2[inl], st.K, threshold_px)
        if kind:
            degenerate.append({"pair": [i, j], "names": [data.image_names[i], data.image_names[j]], "kind": kind,
                               "homography_share": round(ratio, 3), "f_inliers": n})
            continue
        try:
            choice, ang = _two_view(data, st, i, j, F, inl)
        except KitInputError:
            continue
        good = choice.in_front & (ang >= min_angle_deg)
        med = float(np.median(ang[choice.in_front])) if choice.in_front.any() else 0.0
        scored.append((int(good.sum()), n, med, (i, j), choice))
    report["degenerate_pairs"] = degenerate
    scored = [sc for sc in scored if sc[0] >= 10]
    if not scored:
        why = "; ".join(f"{d['names'][0]}-{d['names'][1]}: {d['kind']} (a homography explains {100 * d['homography_share']:.0f} % "
                        "of the matches)" for d in degenerate[:6])
        raise KitInputError(
            f"no image pair can start the reconstruction: none has {min_inliers} or more RANSAC inliers with 10 or more "
            f"points triangulated at {min_angle_deg} degrees or more"
            + (f". Degenerate pairs: {why}. Take photos from different positions (not only turning the camera) "
               "and of a scene that is not a single plane" if degenerate else
               ": the matches are too few or too noisy")
        )
    scored.sort(key=lambda s: (s[0], s[1]), reverse=True)
    return scored


def _triangulate_new(st: _State, new: int, min_angle_deg: float, max_reproj_px: float, refine: bool) -> int:
    """Triangulate tracks seen in image ``new`` and at least one other registered image."""
    from course_lib.sfm.triangulation import triangulate_linear, triangulate_nonlinear

    regs = [k for k in np.flatnonzero(st.registered) if k != new]
    todo = ~st.has_X & st.candidate[:, new]
    C = st.centers()
    P_new = projection_matrix(st.K, st.R[new], st.t[new])
    X0 = np.full((st.T, 3), np.nan)
    # widest baseline first: each track is triangulated from the new image and its farthest partner
    regs.sort(key=lambda k: -np.linalg.norm(C[k] - C[new]))
    for k in regs:
        js = np.flatnonzero(todo & st.candidate[:, k] & ~np.isfinite(X0).all(axis=1))
        if len(js) == 0:
            continue
        X0[js] = triangulate_linear(P_new, projection_matrix(st.K, st.R[k], st.t[k]), st.uv[js, new], st.uv[js, k])
    js = np.flatnonzero(np.isfinite(X0).all(axis=1))
    if len(js) == 0:
        return 0
    return _refine_and_accept(st, js, X0[js], min_angle_deg, max_reproj_px, triangulate_nonlinear if refine else None)


def _retriangulate_and_complete(st: _State, min_angle_deg: float, max_reproj_px: float) -> dict:
    """After the last registration: triangulate tracks that failed earlier, and give back rejected observations that fit.

    * **Re-triangulation**: a track without a point that is seen in two or more registered images
      gets all its observations back and is triangulated again (linear from its two observing
      cameras farthest apart, with the angle and reprojection tests of :func:`_refine_and_accept`;
      the final BA refines it): early on, its cameras may have been poorly placed.
    * **Track completion**: an observation of a triangulated point that was rejected earlier
      (it reprojected badly from a point or camera that has moved since) is used again if it now
      reprojects within ``max_reproj_px``.
    """
    from course_lib.sfm.triangulation import triangulate_linear

    regs = np.flatnonzero(st.registered)
    seen = st.visible & st.registered[None, :]
    # track completion
    rejected = seen & ~st.candidate & st.has_X[:, None]
    E = reprojection_error_matrix(st.K, st.R, st.t, st.X, np.where(rejected[..., None], st.uv, np.nan))
    back = rejected & (E <= max_reproj_px)
    st.candidate |= back
    # re-triangulation
    todo = ~st.has_X & (seen.sum(axis=1) >= 2)
    st.candidate[np.ix_(todo, regs)] |= st.visible[np.ix_(todo, regs)]
    C = st.centers()
    X0 = np.full((st.T, 3), np.nan)
    pairs = sorted(((a, b) for ia, a in enumerate(regs) for b in regs[ia + 1:]), key=lambda ab: -np.linalg.norm(C[ab[0]] - C[ab[1]]))
    for a, b in pairs:  # widest baseline first
        js = np.flatnonzero(todo & seen[:, a] & seen[:, b] & ~np.isfinite(X0).all(axis=1))
        if len(js):
            X0[js] = triangulate_linear(projection_matrix(st.K, st.R[a], st.t[a]), projection_matrix(st.K, st.R[b], st.t[b]),
                                        st.uv[js, a], st.uv[js, b])
    js = np.flatnonzero(np.isfinite(X0).all(axis=1))
    # linear points only: the final BA refines them with everything else
    n_new = _refine_and_accept(st, js, X0[js], min_angle_deg, max_reproj_px, None) if len(js) else 0
    return {"observations_back": int(back.sum()), "tracks_tried": int(todo.sum()), "points_new": int(n_new)}


def _refine_and_accept(st: _State, js, X0, min_angle_deg, max_reproj_px, triangulate_nonlinear) -> int:
    """Check linearly triangulated tracks ``js`` against all registered views, refine, keep the good ones.

    Observations that reproject farther than ``max_reproj_px`` from the linear estimate are
    dropped, the point is refined non-linearly over the remaining ones, checked again, and kept if
    at least two observations in front of their cameras remain and its triangulation angle is at
    least ``min_angle_deg``. Dropped observations are rejected for good.
    """
    regs = np.flatnonzero(st.registered)
    good_X0 = np.isfinite(X0).all(axis=1)
    js, X0 = js[good_X0], X0[good_X0]
    if len(js) == 0:
        return 0
    mask = st.candidate[js][:, regs]
    uv = np.where(mask[..., None], st.uv[js][:, regs], np.nan)
    E = reprojection_error_matrix(st.K, st.R[regs], st.t[regs], X0, uv)
    uv[~(E <= max_reproj_px)] = np.nan
    two = np.isfinite(uv).all(axis=2).sum(axis=1) >= 2
    X = X0.copy()
    if two.any() and triangulate_nonlinear is not None:
        X[two] = triangulate_nonlinear(st.K, st.R[regs], st.t[regs], uv[two], X0[two])
    E = reprojection_error_matrix(st.K, st.R[regs], st.t[regs], X, uv)
    ok_obs = E <= max_reproj_px
    ang = triangulation_angles_deg(X, st.centers()[regs], ok_obs)
    ok = (ok_obs.sum(axis=1) >= 2) & (ang >= min_angle_deg) & np.isfinite(X).all(axis=1)
    rejected = mask & ~ok_obs
    sub = st.candidate[js]
    sub[:, regs] &= ~rejected
    st.candidate[js] = sub
    st.X[js[ok]] = X[ok]
    return int(ok.sum())


def _register(st: _State, i: int, rng, threshold_px: float, min_inliers: int):
    """PnP RANSAC + non-linear PnP for image ``i``: ``(info, None)`` or ``(None, why it failed)``."""
    from course_lib.sfm.pnp import pnp_nonlinear, pnp_ransac

    js = np.flatnonzero(st.has_X & st.candidate[:, i])
    need = max(6, min_inliers)
    if len(js) < need:
        return None, f"too few 2D-3D matches: {len(js)} of its features see triangulated points, PnP needs {need}"
    try:
        res = pnp_ransac(st.X[js], st.uv[js, i], st.K, rng, threshold_px=threshold_px)
    except KitInputError as exc:
        return None, f"PnP RANSAC failed on {len(js)} 2D-3D matches ({exc})"
    inl = np.asarray(res.inliers, bool)
    if inl.sum() < min_inliers:
        return None, f"too few PnP inliers: {int(inl.sum())} of {len(js)} 2D-3D matches within {threshold_px} px, need {min_inliers}"
    R, t = pnp_nonlinear(st.X[js[inl]], st.uv[js[inl], i], st.K, res.R_cw, res.t_cw)
    st.R[i], st.t[i] = R, t
    st.registered[i] = True
    st.candidate[js[~inl], i] = False
    return {"correspondences": int(len(js)), "pnp_inliers": int(inl.sum()), "ransac_iterations": int(res.n_iters)}, None


def _filter(st: _State, max_reproj_px: float, min_angle_deg: float) -> dict:
    """Drop observations that reproject badly, then points with < 2 observations or a small angle."""
    E = st.errors()
    bad = st.inlier & ~(E <= max_reproj_px)
    st.candidate &= ~bad
    inl = st.inlier
    ang = triangulation_angles_deg(np.where(st.has_X[:, None], st.X, 0.0), np.nan_to_num(st.centers()), inl)
    drop = st.has_X & ((inl.sum(axis=1) < 2) | (ang < min_angle_deg))
    st.X[drop] = np.nan
    return {"observations_removed": int(bad.sum()), "points_removed": int(drop.sum())}


#: The final BA leaves out two-view points when every camera keeps this many observations of points seen three or more times.
MIN_MULTIVIEW_OBSERVATIONS = 30


def _multiview_points(st: _State) -> np.ndarray | None:
    """``(T,)`` points seen in 3+ images, or None when some camera has too few of them.

    A point seen in two images cannot reveal a wrong match: any pixel near the epipolar line
    triangulates to a point that fits both exactly (on synthetic scenes with 30 % random outliers,
    a third of the two-view points hold one). So where every camera has at least
    :data:`MIN_MULTIVIEW_OBSERVATIONS` observations of points seen three or more times, the final
    BA refines the cameras with those only, and the two-view points are refined afterwards with
    the cameras fixed (they stay in the model). With a robust loss (heavy-tailed errors, as on
    real photos, where most points are two-view points) a last BA over all points follows.
    """
    n = st.inlier.sum(axis=1)
    multi = n >= 3
    cams = np.flatnonzero(st.registered)
    if not (st.inlier[multi][:, cams].sum(axis=0) >= MIN_MULTIVIEW_OBSERVATIONS).all() or multi[st.has_X].all():
        return None
    return multi


def _refine_points(st: _State, points: np.ndarray) -> int:
    """Non-linear triangulation of the ``(T,)`` bool ``points`` with the cameras fixed; returns how many."""
    from course_lib.sfm.triangulation import triangulate_nonlinear

    js = np.flatnonzero(points & st.has_X)
    if len(js) == 0:
        return 0
    regs = np.flatnonzero(st.registered)
    uv = np.where(st.inlier[js][:, regs][..., None], st.uv[js][:, regs], np.nan)
    st.X[js] = triangulate_nonlinear(st.K, st.R[regs], st.t[regs], uv, st.X[js])
    return int(len(js))


def _bundle(st: _State, ref: int, loss: str, f_scale: float, max_iterations: int, ftol: float = 1e-4,
            points: np.ndarray | None = None) -> dict:
    """Bundle adjustment of the registered cameras and the points (all, or the ``(T,)`` bool ``points``)."""
    cams = np.flatnonzero(st.registered)
    pts = np.flatnonzero(st.has_X if points is None else st.has_X & points)
    inl = st.inlier
    uv = np.where(inl[np.ix_(pts, cams)][..., None], st.uv[np.ix_(pts, cams)], np.nan)
    ref_local = int(np.flatnonzero(cams == ref)[0])
    res = bundle_adjust(
        st.K, st.R[cams], st.t[cams], st.X[pts], uv, loss=loss, f_scale=f_scale, max_iterations=max_iterations,
        ref_camera=ref_local, ftol=ftol, xtol=1e-10,
    )
    st.R[cams], st.t[cams], st.X[pts] = res.R_cw, res.t_cw, res.X
    return {
        "iterations": res.n_iterations,
        "rms_before": round(res.initial_rms, 4),
        "rms_after": round(res.final_rms, 4),
        "seconds": round(res.seconds, 3),
        "gauge": res.gauge,
    }


#: Median of the Rayleigh distribution over sigma: the reprojection error (a 2-D distance) of
#: observations with Gaussian noise sigma per coordinate has median sigma * sqrt(2 ln 2).
_RAYLEIGH_MEDIAN = float(np.sqrt(2.0 * np.log(2.0)))


#: Share of observations beyond 3 sigma above which the errors count as heavy-tailed (Gaussian
#: noise puts about 1 % there, SIFT matches 10-16 % on the course data and the embedded scene).
HEAVY_TAIL_SHARE = 0.08


def _final_thresholds(st: _State, max_reproj_px, f_scale, loss: str) -> tuple[float, float, float, float, str]:
    """Threshold, loss and loss scale of the final BA: as given, or from the error distribution.

    The noise ``sigma`` (pixels per coordinate) is estimated robustly from the median
    reprojection error of the current inlier observations. ``None`` threshold: ``4 sigma`` within
    [1, 4] px (about 1 in 3000 good observations is beyond 4 sigma). ``loss="auto"``: the Cauchy
    loss where the errors have a heavy tail (more than :data:`HEAVY_TAIL_SHARE` of them beyond
    ``3 sigma``, as SIFT's have), plain least squares (``"linear"``, the most accurate for
    Gaussian noise) otherwise. ``None`` scale: ``2 sigma``, at least 0.3 px.

    Returns:
        ``(threshold_px, f_scale_px, sigma_px, tail_share, loss)``.
    """
    e = st.errors()
    e = e[np.isfinite(e)]
    sigma = float(np.median(e) / _RAYLEIGH_MEDIAN) if len(e) else 1.0
    tail = float(np.mean(e > 3.0 * sigma)) if len(e) else 0.0
    thr = float(np.clip(4.0 * sigma, 1.0, 4.0)) if max_reproj_px is None else float(max_reproj_px)
    fs = max(0.3, 2.0 * sigma) if f_scale is None else float(f_scale)
    if loss == "auto":
        loss = "cauchy" if tail > HEAVY_TAIL_SHARE else "linear"
    return thr, fs, sigma, tail, loss


def run_sfm(
    data,
    rng: np.random.Generator,
    *,
    f_threshold_px: float = 2.0,
    pnp_threshold_px: float = 8.0,
    max_reproj_px: float = 4.0,
    final_max_reproj_px: float | None = None,
    min_angle_deg: float = 1.0,
    init_min_angle_deg: float = 2.0,
    min_pair_inliers: int = 50,
    min_pnp_inliers: int = 20,
    bundle_adjustment: str = "incremental",
    ba_loss: str = "huber",
    ba_f_scale: float = 1.0,
    ba_max_iterations: int = 10,
    final_ba_loss: str = "auto",
    final_ba_f_scale: float | None = None,
    initial_pair: tuple[int, int] | None = None,
    verbose: bool = False,
) -> Reconstruction:
    """Incremental SfM: RANSAC on F, initial pair, triangulation, PnP registration, bundle adjustment.

    Args:
        data: a :class:`course_lib.data.p3.P3Data` (``K``, ``image_names``, ``track_uv``,
            ``track_rgb``, ``matches``; ``image_size`` if the images are present).
        rng: seeded ``numpy.random.Generator`` (RANSAC on F and PnP draw from it).
        f_threshold_px: RANSAC threshold on the Sampson distance for the pairs (pixels); only
            matches within it join tracks.
        pnp_threshold_px: PnP RANSAC threshold on the reprojection error (pixels).
        max_reproj_px: observations reprojecting farther than this are dropped during the run.
        final_max_reproj_px: the threshold of the last filtering before the final BA; ``None``
            (default): 4 times the noise level estimated from the median reprojection error,
            within [1, 4] px.
        min_angle_deg: smallest triangulation angle for a point to be kept.
        init_min_angle_deg: angle a point of the initial pair must have to count in its score.
        min_pair_inliers: pairs with fewer RANSAC inliers cannot be the initial pair.
        min_pnp_inliers: an image is registered only with at least this many PnP inliers.
        bundle_adjustment: ``"incremental"`` (after every registration and at the end),
            ``"final"`` (once at the end) or ``"none"`` (the result *before* bundle adjustment,
            the starting point of notebook 05).
        ba_loss, ba_f_scale: robust loss of the intermediate bundle adjustments.
        ba_max_iterations: iteration cap of each bundle adjustment (twice that for the final one).
        final_ba_loss, final_ba_f_scale: loss of the final bundle adjustment, run after the
            observations beyond ``final_max_reproj_px`` were removed. ``"auto"`` (default): the
            Cauchy loss at ``f_scale`` (``None``: twice the estimated noise, at least 0.3 px) when
            the errors have a heavy tail, as SIFT localization errors do (on the embedded scene it
            halves the rotation error against the ground truth compared with plain least
            squares), and plain least squares for Gaussian-like errors, where it is the most
            accurate; or any loss of :func:`~course_lib.sfm.bundle_adjustment.bundle_adjust`.
        initial_pair: force the initial pair ``(i, j)`` (0-based) instead of choosing it.
        verbose: print one line per stage.

    Returns:
        :class:`Reconstruction`; ``report`` holds ``pairs`` (matches / RANSAC inliers per pair),
        ``tracks`` (raw and verified tracks, refused links), ``degenerate_pairs`` (pairs left out of
        the initial-pair choice: ``"pure rotation"`` or ``"planar"``), ``left_out`` (each
        unregistered image with the reason), ``initial_pair``, ``stages`` (one entry per registered image: PnP inliers, new points,
        points, reprojection error before and after BA, seconds), ``final`` (registered images,
        points, observations, mean / median / rms reprojection error) and ``seconds`` per stage.

    Raises:
        KitInputError: bad data (no pair with enough inliers, malformed arrays) or options.

    Introduced in ``notebooks/05_bundle_adjustment.ipynb``.
    """
    with single_threaded_blas():
        return _run_sfm(
            data, rng, f_threshold_px, pnp_threshold_px, max_reproj_px, final_max_reproj_px, min_angle_deg,
            init_min_angle_deg, min_pair_inliers, min_pnp_inliers, bundle_adjustment, ba_loss, ba_f_scale,
            ba_max_iterations, final_ba_loss, final_ba_f_scale, initial_pair, verbose,
        )


def _run_sfm(
    data, rng, f_threshold_px, pnp_threshold_px, max_reproj_px, final_max_reproj_px, min_angle_deg,
    init_min_angle_deg, min_pair_inliers, min_pnp_inliers, bundle_adjustment, ba_loss, ba_f_scale,
    ba_max_iterations, final_ba_loss, final_ba_f_scale, initial_pair, verbose,
) -> Reconstruction:
    t_start = time.perf_counter()
    if not isinstance(rng, np.random.Generator):
        raise KitInputError(f"rng must be a numpy.random.Generator (np.random.default_rng(seed)), got {type(rng).__name__}")
    if bundle_adjustment not in ("incremental", "final", "none"):
        raise KitInputError(f"bundle_adjustment={bundle_adjustment!r}: expected 'incremental', 'final' or 'none'")
    for attr in ("K", "image_names", "track_uv", "track_rgb", "matches"):
        if not hasattr(data, attr):
            raise KitInputError(f"data has no attribute {attr!r}: pass the P3Data returned by course_lib.data.p3.read_p3")
    K = intrinsics(data.K)
    uv = np.asarray(data.track_uv, float)
    M = len(data.image_names)
    if uv.ndim != 3 or uv.shape[1:] != (M, 2):
        raise KitInputError(f"data.track_uv has shape {uv.shape}: expected (T, {M}, 2) for {M} images")
    if M < 2:
        raise KitInputError(f"data has {M} image(s): SfM needs at least two")
    say = print if verbose else (lambda *a, **k: None)

    report: dict = {"n_images": M, "options": {
        "f_threshold_px": f_threshold_px, "pnp_threshold_px": pnp_threshold_px, "max_reproj_px": max_reproj_px,
        "final_max_reproj_px": final_max_reproj_px, "min_angle_deg": min_angle_deg,
        "bundle_adjustment": bundle_adjustment, "ba_loss": ba_loss, "ba_f_scale": ba_f_scale,
        "final_ba_loss": final_ba_loss, "final_ba_f_scale": final_ba_f_scale}}
    seconds: dict[str, float] = {}

    # 1. verified matches and their tracks ---------------------------------------------------------
    t0 = time.perf_counter()
    pairs, tracks = _verified_tracks(data, rng, f_threshold_px, 16, report)
    st = _State(tracks.uv, K)
    report["n_tracks"] = st.T
    seconds["ransac_F"] = time.perf_counter() - t0
    tr = report["tracks"]
    say(f"RANSAC on F: {len(pairs)} pairs verified; {tr['verified_tracks']} tracks from {tr['verified_matches']} inlier matches "
        f"({tr['refused_links']} links refused: they joined two features of one image)")

    # 2. initial pair ----------------------------------------------------------------------------
    t0 = time.perf_counter()
    if initial_pair is not None:
        a, b = sorted(int(v) for v in initial_pair)
        if (a, b) not in pairs:
            raise KitInputError(f"initial_pair={initial_pair}: that pair has no RANSAC result (too few matches?)")
        choice, ang = _two_view(data, st, a, b, *pairs[(a, b)])
        scored = [(int((choice.in_front & (ang >= init_min_angle_deg)).sum()), int(pairs[(a, b)][1].sum()), 0.0, (a, b), choice)]
        report["degenerate_pairs"] = []
    else:
        scored = _choose_initial_pair(data, st, pairs, min_pair_inliers, init_min_angle_deg, f_threshold_px, report)
    score, n_inl, _, (a, b), choice = scored[0]
    st.R[a], st.t[a] = np.eye(3), np.zeros(3)
    st.R[b], st.t[b] = choice.R_cw, choice.t_cw
    st.registered[[a, b]] = True
    from course_lib.sfm.triangulation import triangulate_linear, triangulate_nonlinear

    js = np.flatnonzero(st.candidate[:, a] & st.candidate[:, b])
    X0 = triangulate_linear(projection_matrix(K, st.R[a], st.t[a]), projection_matrix(K, st.R[b], st.t[b]), st.uv[js, a], st.uv[js, b])
    n_new = _refine_and_accept(st, js, X0, min_angle_deg, max_reproj_px, triangulate_nonlinear)
    report["initial_pair"] = {
        "images": [a, b],
        "names": [data.image_names[a], data.image_names[b]],
        "ransac_inliers": n_inl,
        "score": score,
        "candidates": [{"images": list(s[3]), "score": s[0], "ransac_inliers": s[1], "median_angle_deg": round(s[2], 2)} for s in scored],
        "points": n_new,
    }
    stages = []
    stage = {"stage": "initial pair", "images": [a, b], "new_points": n_new, "points": int(st.has_X.sum()),
             "reprojection_before_ba": st.observation_stats()}
    if bundle_adjustment == "incremental":
        stage["ba"] = _bundle(st, a, ba_loss, ba_f_scale, ba_max_iterations)
        stage["filter"] = _filter(st, max_reproj_px, min_angle_deg)
        stage["reprojection_after_ba"] = st.observation_stats()
    stage["seconds"] = round(time.perf_counter() - t0, 3)
    stages.append(stage)
    seconds["initial_pair"] = time.perf_counter() - t0
    say(f"initial pair {data.image_names[a]}, {data.image_names[b]}: {n_new} points")

    # 3-5. register the other images --------------------------------------------------------------
    t_reg = time.perf_counter()
    failed: set[int] = set()
    reasons: dict[int, str] = {}
    while True:
        todo = [i for i in range(M) if not st.registered[i] and i not in failed]
        if not todo:
            break
        counts = {i: int((st.has_X & st.candidate[:, i]).sum()) for i in todo}
        i = max(todo, key=lambda k: (counts[k], -k))
        t0 = time.perf_counter()
        info, why = _register(st, i, rng, pnp_threshold_px, min_pnp_inliers)
        if info is None:
            failed.add(i)
            reasons[i] = why
            stages.append({"stage": "register", "image": i, "name": data.image_names[i], "registered": False,
                           "correspondences": counts[i], "note": why})
            say(f"not registered (yet): {data.image_names[i]}: {why}")
            continue
        n_new = _triangulate_new(st, i, min_angle_deg, max_reproj_px, refine=bundle_adjustment != "incremental")
        stage = {"stage": "register", "image": i, "name": data.image_names[i], "registered": True, **info,
                 "new_points": n_new, "points": int(st.has_X.sum()), "reprojection_before_ba": st.observation_stats()}
        if bundle_adjustment == "incremental":
            stage["ba"] = _bundle(st, a, ba_loss, ba_f_scale, ba_max_iterations)
            stage["filter"] = _filter(st, max_reproj_px, min_angle_deg)
            stage["reprojection_after_ba"] = st.observation_stats()
        stage["points_after"] = int(st.has_X.sum())
        stage["seconds"] = round(time.perf_counter() - t0, 3)
        stages.append(stage)
        failed.clear()  # new points may let a failed image in now
        say(f"registered {data.image_names[i]}: {info['pnp_inliers']}/{info['correspondences']} PnP inliers, "
            f"{n_new} new points, {int(st.has_X.sum())} points")
    seconds["registration"] = time.perf_counter() - t_reg
    verified = {k for key in pairs for k in key}
    for i in np.flatnonzero(~st.registered):
        if i not in verified:
            reasons[i] = "no verified matches with any other image (no pair passed RANSAC on F with enough inliers)"
        report.setdefault("left_out", []).append({"image": int(i), "name": data.image_names[i], "reason": reasons.get(i, "not registered")})
        say(f"left out: {data.image_names[i]}: {reasons.get(i, 'not registered')}")
    report.setdefault("left_out", [])

    # final bundle adjustment ------------------------------------------------------------------------
    t0 = time.perf_counter()
    final_stage = {"stage": "final", "reprojection_before_ba": st.observation_stats()}
    if bundle_adjustment != "none":
        if bundle_adjustment == "final":
            final_stage["ba_robust"] = _bundle(st, a, ba_loss, ba_f_scale, 2 * ba_max_iterations)
        final_stage["retriangulation"] = _retriangulate_and_complete(st, min_angle_deg, max_reproj_px)
        thr, fs, sigma, tail, loss = _final_thresholds(st, final_max_reproj_px, final_ba_f_scale, final_ba_loss)
        final_stage["noise_sigma_px"], final_stage["tail_share"] = round(sigma, 4), round(tail, 4)
        final_stage["ba_loss"] = loss
        final_stage["max_reproj_px"], final_stage["ba_f_scale"] = round(thr, 4), round(fs, 4)
        final_stage["filter"] = _filter(st, thr, min_angle_deg)
        multi = _multiview_points(st)
        final_stage["ba"] = _bundle(st, a, loss, fs, 2 * ba_max_iterations, ftol=1e-6, points=multi)
        if multi is not None:
            final_stage["ba"]["two_view_points_refined_after"] = _refine_points(st, ~multi)
            if loss != "linear":
                # a robust loss bounds the pull of a wrong two-view point: let them all take part at the end
                final_stage["filter_mid"] = _filter(st, thr, min_angle_deg)
                final_stage["ba_all_points"] = _bundle(st, a, loss, fs, 2 * ba_max_iterations, ftol=1e-6)
        final_stage["filter_after"] = _filter(st, thr, min_angle_deg)
        final_stage["reprojection_after_ba"] = st.observation_stats()
    final_stage["seconds"] = round(time.perf_counter() - t0, 3)
    stages.append(final_stage)
    seconds["final_ba"] = time.perf_counter() - t0
    seconds["total"] = time.perf_counter() - t_start

    rec = Reconstruction(
        K=K,
        image_names=list(data.image_names),
        image_size=_image_size(data),
        registered=st.registered.copy(),
        R_cw=st.R.copy(),
        t_cw=st.t.copy(),
        X=st.X.copy(),
        rgb=tracks.rgb.copy(),
        track_uv=st.uv.copy(),
        inlier=st.inlier.copy(),
        report=report,
    )
    stats = rec.error_stats()
    report["stages"] = stages
    report["final"] = {
        "registered_images": rec.n_registered,
        "registered": [data.image_names[i] for i in np.flatnonzero(rec.registered)],
        "left_out": {d["name"]: d["reason"] for d in report["left_out"]},
        "points": rec.n_points,
        "observations": int(rec.inlier.sum()),
        "mean_track_length": round(float(rec.inlier.sum() / max(rec.n_points, 1)), 3),
        "mean_reprojection_error_px": round(stats["mean"], 4),
        "median_reprojection_error_px": round(stats["median"], 4),
        "rms_reprojection_error_px": round(stats["rms"], 4),
        "max_reprojection_error_px": round(stats["max"], 4),
    }
    report["seconds"] = {k: round(v, 3) for k, v in seconds.items()}
    say(f"final: {rec.n_registered}/{M} images, {rec.n_points} points, mean reprojection error {stats['mean']:.3f} px, "
        f"{seconds['total']:.1f} s")
    return rec
