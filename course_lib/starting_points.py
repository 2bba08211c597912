"""Where each notebook starts: the reference result of the step before it.

Every notebook can start from the reference output of the step before, so a student who is stuck
on step 2 can still do step 3, and each step is graded on its own. For the embedded scene
(``data/synthetic-building``) these results are read from the stored fixtures (made from the
reference by ``python -m course_lib fixtures``), so they work in the student kit, which holds no
reference solution. For another P3 folder (e.g. ``course_data("wpi")``) they are computed with the
reference library, which only the instructor's kit has; the student kit then says so.

* notebook 02: :func:`two_view_step` (F and the inliers of notebook 01);
* notebook 03: :func:`triangulation_input` (E and the four pose candidates of notebook 02);
* notebook 04: :func:`pnp_input` (the two-view reconstruction of notebook 03 and the next image's
  2D-3D matches);
* notebook 05: :func:`bundle_adjustment_input` (the incremental reconstruction of notebooks 01-04
  before bundle adjustment) and :func:`observation_arrays`.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from course_lib.conventions import observed_entries
from course_lib.data.p3 import read_p3
from course_lib.fixtures import load_fixture
from course_lib.paths import EMBEDDED_SFM

__all__ = [
    "STEP_PAIR",
    "STEP_THRESHOLD_PX",
    "STEP_SEED",
    "NEW_IMAGE",
    "TwoViewStep",
    "two_view_step",
    "two_view_input",
    "triangulation_input",
    "two_view_reconstruction",
    "correspondences_2d3d",
    "pnp_input",
    "reconstruction_before_ba",
    "bundle_adjustment_input",
    "observation_arrays",
    "relative_truth",
]


#: The image pair of the embedded scene that notebooks 01 and 02 work on (0-based: images 1 and 2).
STEP_PAIR = (0, 1)


#: RANSAC threshold (pixels) and seed for the step result of the embedded pair.
STEP_THRESHOLD_PX = 1.0


#: Seed of the RANSAC generator of the step result.
STEP_SEED = 0


class TwoViewStep(dict):
    """The reference result of notebook 01 for one image pair (a dict with attribute access).

    Keys: ``x1 (N, 2)``, ``x2 (N, 2)`` (all unique correspondences of the pair), ``F (3, 3)``
    (RANSAC + refit on the inliers), ``inliers (N,)`` bool, ``K (3, 3)``, ``pair`` (i, j), ``source``.
    """

    __getattr__ = dict.__getitem__


def two_view_step(data_folder=None, pair: tuple[int, int] = STEP_PAIR) -> TwoViewStep:
    """The reference F and inlier mask of notebook 01 for an image pair, to start notebook 02 from.

    For the embedded scene (``data/synthetic-building``, the default) the result is read from the
    stored fixture, so it works without the reference solutions. For another P3 folder (e.g.
    ``course_data("wpi")``) it is computed with the reference RANSAC (seed 0, threshold 1 px);
    that needs the full kit.

    Args:
        data_folder: a P3 folder; default the embedded scene.
        pair: 0-based image indices ``(i, j)``, ``i < j``.

    Returns:
        :class:`TwoViewStep` with ``x1, x2, F, inliers, K, pair, source``.

    Introduced in notebooks/02_essential_matrix_and_pose.ipynb.
    """
    folder = Path(EMBEDDED_SFM if data_folder is None else data_folder)
    pair = (int(pair[0]), int(pair[1]))
    if folder.resolve() == Path(EMBEDDED_SFM).resolve() and pair == STEP_PAIR:
        f = load_fixture("fundamental_step")
        if "building_F_ransac" not in f:
            raise FileNotFoundError(
                "the fundamental_step fixture has no result for the embedded scene; rebuild it with: "
                "python -m course_lib fixtures fundamental_step"
            )
        return TwoViewStep(
            x1=f["building_x1"], x2=f["building_x2"], F=f["building_F_ransac"], inliers=f["building_inliers"].astype(bool),
            K=f["building_K"], pair=pair, source="stored reference result (fixture 'fundamental_step')",
        )
    try:
        from course_lib.sfm.fundamental import ransac_fundamental
    except ImportError as exc:  # a student release without the reference solutions
        raise FileNotFoundError(
            f"no stored step result for {folder} pair {pair}: use your own ransac_fundamental from notebook 01 ({exc})"
        ) from None
    data = read_p3(folder, require_images=False)
    m = data.matches[pair]
    res = ransac_fundamental(m.x1, m.x2, np.random.default_rng(STEP_SEED), threshold_px=STEP_THRESHOLD_PX)
    return TwoViewStep(x1=m.x1, x2=m.x2, F=res.F, inliers=res.inliers, K=data.K, pair=pair,
                       source="computed with the reference ransac_fundamental (seed 0, threshold 1 px)")


# --------------------------------------------------------------------------- notebook 03


def two_view_input(folder, pair: tuple[int, int] = STEP_PAIR, seed: int = STEP_SEED) -> dict[str, np.ndarray]:
    """Step 2's reference result for one image pair, computed with the reference library.

    Args:
        folder: a P3 folder (the embedded scene or ``course_data("wpi")``).
        pair: 0-based image indices ``(i, j)``, ``i < j``.
        seed: seed of the RANSAC on F.

    Returns:
        dict with ``K (3, 3)``, ``pair (2,)``, ``F (3, 3)``, ``E (3, 3)``, ``x1, x2 (N, 2)`` (the RANSAC
        inliers), ``track_ids (N,)`` (-1 if not in a track), ``rgb (N, 3)`` uint8, ``R_candidates (4, 3, 3)``,
        ``C_candidates (4, 3)``, ``n_matches`` (before RANSAC).
    """
    try:
        from course_lib.sfm import essential, fundamental
    except ModuleNotFoundError as exc:  # the student release has no reference solutions
        raise RuntimeError(
            f"computing the step input for {folder} needs the reference library ({exc.name}); "
            "use the embedded data (DATA = EMBEDDED_SFM) or your own functions from notebooks 01-02"
        ) from None
    data = read_p3(folder)
    i, j = pair
    m = data.matches[(i, j)]
    # the same RANSAC setting as notebook 01's step result (two_view_step)
    res = fundamental.ransac_fundamental(m.x1, m.x2, np.random.default_rng(seed), threshold_px=STEP_THRESHOLD_PX)
    E = essential.essential_from_fundamental(res.F, data.K)
    R, C = essential.pose_candidates(E)
    inl = res.inliers
    return {
        "K": data.K,
        "pair": np.array(pair),
        "F": res.F,
        "E": E,
        "x1": m.x1[inl],
        "x2": m.x2[inl],
        "track_ids": m.track_ids[inl],
        "rgb": m.rgb[inl],
        "R_candidates": R,
        "C_candidates": C,
        "n_matches": np.array(len(m.x1)),
    }


def relative_truth(folder, pair) -> tuple[np.ndarray, np.ndarray] | None:
    """True pose of camera j in camera i's frame, translation scaled to unit length (or None)."""
    gt = Path(folder) / "ground_truth.json"
    if not gt.exists():
        return None
    from course_lib.data.building import load_ground_truth  # deferred: cv2 + the renderer, not at every check import

    _, _, R_cw, t_cw = load_ground_truth(folder)
    i, j = pair
    R = R_cw[j] @ R_cw[i].T
    t = t_cw[j] - R @ t_cw[i]
    return R, t / np.linalg.norm(t)


def triangulation_input(folder=None) -> dict[str, np.ndarray]:
    """Notebook 03's starting point: step 2's reference result for the pair :data:`STEP_PAIR`.

    Args:
        folder: ``None`` or the embedded scene: read the stored fixture (no reference needed);
            another P3 folder (e.g. ``course_data("wpi")``): compute it with :func:`two_view_input`.

    Returns:
        the dict of :func:`two_view_input` (for the embedded scene also ``true_R_cw``,
        ``true_t_cw``: the true relative pose, unit translation).
    """
    if folder is None or Path(folder).resolve() == EMBEDDED_SFM.resolve():
        return load_fixture("triangulation_step")
    return two_view_input(folder)


# --------------------------------------------------------------------------- notebook 04


#: The image of the embedded scene registered in notebook 04 (0-based); the pair is (0, 1).
NEW_IMAGE = 2


def correspondences_2d3d(track_ids: np.ndarray, X: np.ndarray, track_uv: np.ndarray, image: int):
    """2D-3D correspondences of one image: reconstructed points whose track is seen in it.

    Args:
        track_ids: ``(N,)`` track id of each reconstructed point (-1: not in a track).
        X: ``(N, 3)`` reconstructed points.
        track_uv: ``(T, M, 2)`` pixels of every track in every image, NaN where unseen
            (:attr:`course_lib.data.p3.P3Data.track_uv`).
        image: 0-based index of the image to register.

    Returns:
        ``X_new (K, 3)``, ``x_new (K, 2)`` and ``ids (K,)`` (their track ids).

    Introduced in notebooks/04_pnp.ipynb
    """
    track_ids = np.asarray(track_ids, int)
    ok = track_ids >= 0
    uv = np.full((len(track_ids), 2), np.nan)
    uv[ok] = track_uv[track_ids[ok], image]
    seen = ok & np.isfinite(uv).all(axis=1)
    return np.asarray(X, float)[seen], uv[seen], track_ids[seen]


def two_view_reconstruction(folder, new_image: int = NEW_IMAGE) -> dict[str, np.ndarray]:
    """Step 3's reference result: the two-view reconstruction of the pair, and the next image's 2D-3D matches.

    Runs the reference chain (in the instructor's kit) on the pair of :func:`triangulation_input`:
    :func:`~course_lib.sfm.triangulation.choose_pose`, then
    :func:`~course_lib.sfm.triangulation.triangulate_nonlinear`, keeping the points in front of
    both cameras.

    Returns:
        dict with ``K``, ``pair (2,)``, ``R_cws (2, 3, 3)``, ``t_cws (2, 3)`` (camera 1 at ``I, 0``,
        ``|t_cws[1]| = 1``), ``X (N, 3)``, ``track_ids (N,)``, ``rgb (N, 3)`` uint8, ``x1, x2 (N, 2)``
        (the pixels of the points in the pair), ``new_image``, ``X_new (K, 3)``,
        ``x_new (K, 2)``, ``ids_new (K,)``.
    """
    try:
        from course_lib.sfm import triangulation as tri
    except ModuleNotFoundError as exc:
        raise RuntimeError(
            f"computing the step input for {folder} needs the reference library ({exc.name}); "
            "use the embedded data (DATA = EMBEDDED_SFM) or your own functions from notebook 03"
        ) from None
    st = triangulation_input(folder)
    K = st["K"]
    ch = tri.choose_pose(st["R_candidates"], st["C_candidates"], K, st["x1"], st["x2"])
    R_cws = np.stack([np.eye(3), ch.R_cw])
    t_cws = np.stack([np.zeros(3), ch.t_cw])
    keep = ch.in_front
    uv = np.stack([st["x1"][keep], st["x2"][keep]], axis=1)
    X = tri.triangulate_nonlinear(K, R_cws, t_cws, uv, ch.X[keep])
    ids = st["track_ids"][keep]
    data = read_p3(folder, require_images=False)
    X_new, x_new, ids_new = correspondences_2d3d(ids, X, data.track_uv, new_image)
    return {"K": K, "pair": st["pair"], "R_cws": R_cws, "t_cws": t_cws, "X": X, "track_ids": ids, "rgb": st["rgb"][keep],
            "x1": uv[:, 0], "x2": uv[:, 1], "new_image": np.array(new_image),
            "X_new": X_new, "x_new": x_new, "ids_new": ids_new}


def pnp_input(folder=None) -> dict[str, np.ndarray]:
    """Notebook 04's starting point: the two-view reconstruction and the next image's 2D-3D matches.

    Args:
        folder: ``None`` or the embedded scene: the stored fixture (no reference needed); another
            P3 folder (e.g. ``course_data("wpi")``): computed with :func:`two_view_reconstruction`.

    Returns:
        the dict of :func:`two_view_reconstruction` (for the embedded scene also the true pose
        ``true_R_cw_new, true_t_cw_new`` of the new image in the reconstruction's frame).
    """
    if folder is None or Path(folder).resolve() == EMBEDDED_SFM.resolve():
        return load_fixture("pnp_step")
    return two_view_reconstruction(folder)


# --------------------------------------------------------------------------- notebook 05


def reconstruction_before_ba(folder, seed: int = STEP_SEED) -> dict[str, np.ndarray]:
    """Steps 1-4 on a P3 folder: the incremental reconstruction before bundle adjustment.

    Runs :func:`course_lib.sfm.pipeline.run_sfm` with ``bundle_adjustment="none"`` (RANSAC on F,
    the initial pair, PnP registration, triangulation; no BA).

    Returns:
        dict with ``K (3, 3)``, ``image_size (2,)`` = (W, H), ``image_names (M,)`` str,
        ``registered (M,)`` bool, ``R_cw (M, 3, 3)``, ``t_cw (M, 3)`` (NaN where unregistered),
        ``X (T, 3)`` (NaN where not triangulated), ``rgb (T, 3)`` uint8, ``track_uv (T, M, 2)``,
        ``inlier (T, M)`` bool (the observations in use), ``initial_pair (2,)``.
    """
    try:
        from course_lib.sfm.pipeline import run_sfm
    except ModuleNotFoundError as exc:
        raise RuntimeError(
            f"computing the step input for {folder} needs the reference library ({exc.name}); "
            "use the embedded data (DATA = EMBEDDED_SFM)"
        ) from None
    data = read_p3(folder)
    rec = run_sfm(data, np.random.default_rng(seed), bundle_adjustment="none")
    return {
        "K": rec.K,
        "image_size": np.array(rec.image_size, dtype=np.int64),
        "image_names": np.array(rec.image_names),
        "registered": rec.registered,
        "R_cw": rec.R_cw,
        "t_cw": rec.t_cw,
        "X": rec.X,
        "rgb": rec.rgb,
        "track_uv": rec.track_uv,
        "inlier": rec.inlier,
        "initial_pair": np.array(rec.report["initial_pair"]["images"], dtype=np.int64),
    }


def bundle_adjustment_input(folder=None) -> dict[str, np.ndarray]:
    """Notebook 05's starting point: the reconstruction of steps 1-4, before bundle adjustment.

    Args:
        folder: ``None`` or the embedded scene: the stored fixture (no reference needed); another
            P3 folder (e.g. ``course_data("wpi")``): computed with :func:`reconstruction_before_ba`.

    Returns:
        the dict of :func:`reconstruction_before_ba`.
    """
    if folder is None or Path(folder).resolve() == EMBEDDED_SFM.resolve():
        return load_fixture("bundle_adjustment_step")
    return reconstruction_before_ba(folder)


def observation_arrays(uv: np.ndarray):
    """``camera_idx (K,)``, ``point_idx (K,)``, ``uv_obs (K, 2)`` of the finite entries of ``uv (N, M, 2)``.

    One entry per observation (V_ij = 1), point by point: the layout of the residuals of bundle
    adjustment (:func:`course_lib.conventions.observed_entries`, in the order notebook 05 unpacks).
    Introduced in notebooks/05_bundle_adjustment.ipynb.
    """
    point_idx, camera_idx, uv_obs = observed_entries(uv)
    return camera_idx, point_idx, uv_obs
