"""The report of one model: what the controller (:mod:`course_lib.sfm.pipeline`) writes down as the mapper works.

The mapper's stage methods (:class:`course_lib.sfm.mapper.IncrementalMapper`) change the model and
return numbers; the controller times each call and hands the numbers to a :class:`MapperReport`,
which keeps the stages in order, adds up the seconds, prints one line per stage when asked to, and
builds the model's ``report`` dict (the ``report.json`` of ``python -m course_lib sfm``).
"""

from __future__ import annotations

import time
from contextlib import contextmanager

__all__ = ["MapperReport"]


class MapperReport:
    """The stages, seconds and printed lines of one model.

    Args:
        names: the image names (index -> name). verbose: print one line per stage.

    Attributes:
        stages: one dict per stage, in order (``"initial pair"``, ``"register"`` (also the failed
            attempts), ``"retriangulate (stalled)"``, ``"final"``, ``"merge"``; the stages of a model
            merged into this one are marked ``"model": "merged"``), each with its ``seconds``.
        seconds: seconds by kind (``initial_pair``, ``registration``, ``final_ba``, ``merge``).
        initial: the initial pair (images, names, RANSAC and pose inliers, score, points).
        candidates: the rows of the initial pairs tried. relaxations: the relaxed settings tried, if any.
        reasons: why an image did not register in this model (its latest attempt), by image index.
    """

    def __init__(self, names, verbose: bool = False):
        self.names, self.verbose = list(names), bool(verbose)
        self.stages: list[dict] = []
        self.seconds: dict[str, float] = {}
        self.initial: dict = {}
        self.candidates: list[dict] = []
        self.relaxations: list[dict] = []
        self.reasons: dict[int, str] = {}

    def say(self, line: str) -> None:
        """Print ``line`` when verbose."""
        if self.verbose:
            print(line)

    @contextmanager
    def timing(self, kind: str):
        """Add the block's seconds to :attr:`seconds` ``[kind]``."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[kind] = self.seconds.get(kind, 0.0) + time.perf_counter() - t0

    # --- the stages -------------------------------------------------------------------------------------

    def start_failed(self, images: tuple[int, int], points: int, need: int) -> None:
        """An initial pair kept ``points`` points, fewer than ``need``: the next candidate is tried."""
        a, b = images
        self.say(f"initial pair {self.names[a]}, {self.names[b]}: only {points} points (need {need}); next candidate")

    def started(self, pair, numbers: dict, seconds: float, search_seconds: float | None = None) -> None:
        """The model started from ``pair`` (:class:`~course_lib.sfm.initial_pair.InitialPair`); ``numbers`` from
        :meth:`~course_lib.sfm.mapper.IncrementalMapper.initialize`, which took ``seconds``; ``search_seconds``: with the
        candidates' scores and the pairs tried before (the stage's seconds in :attr:`seconds`)."""
        a, b = pair.images
        self.stages.append({"stage": "initial pair", "images": [a, b], **numbers, "seconds": round(seconds, 3)})
        self.initial = {"images": [a, b], "names": [self.names[a], self.names[b]], "ransac_inliers": pair.inliers,
                        "pose_inliers": pair.pose_inliers, "score": pair.score, "points": numbers["new_points"]}
        self.seconds["initial_pair"] = seconds if search_seconds is None else search_seconds
        self.say(f"initial pair {self.names[a]}, {self.names[b]}: {numbers['new_points']} points")

    def registered(self, i: int, numbers: dict, seconds: float) -> None:
        """Image ``i`` registered; ``numbers`` from :meth:`~course_lib.sfm.mapper.IncrementalMapper.add_image`."""
        self.stages.append({"stage": "register", "image": i, "name": self.names[i], "registered": True, **numbers,
                            "seconds": round(seconds, 3)})
        how = (f"{numbers['pnp_inliers']}/{numbers['correspondences']} PnP inliers" if "structure_less" not in numbers else
               f"from its matches with {', '.join(numbers['structure_less'])} ({numbers['pnp_inliers']}/"
               f"{numbers['correspondences']} fit; too few points for PnP)")
        self.say(f"registered {self.names[i]}: {how}, {numbers['new_points']} new points, {numbers['points_after']} points")

    def not_registered(self, i: int, correspondences: int, why: str) -> None:
        """Image ``i`` did not register (yet), for the reason ``why``."""
        self.reasons[i] = why
        self.stages.append({"stage": "register", "image": i, "name": self.names[i], "registered": False,
                            "correspondences": correspondences, "note": why})
        self.say(f"not registered (yet): {self.names[i]}: {why}")

    def retriangulated(self, numbers: dict, seconds: float) -> None:
        """Registration stalled and the model was re-triangulated; ``numbers`` from ``retriangulate``."""
        self.stages.append({"stage": "retriangulate (stalled)", **numbers, "seconds": round(seconds, 3)})

    def finished(self, numbers: dict, seconds: float) -> None:
        """The final stage (re-triangulation, filtering, final BA); ``numbers`` from ``finish``."""
        self.stages.append({"stage": "final", **numbers, "seconds": round(seconds, 3)})
        self.seconds["final_ba"] = self.seconds.get("final_ba", 0.0) + seconds

    def absorb(self, later: "MapperReport", numbers: dict, seconds: float) -> "MapperReport":
        """This (earlier) model's report after the ``later`` model was merged into it (``numbers`` from
        :meth:`~course_lib.sfm.mapper.IncrementalMapper.merge`): the later model's stages follow this
        one's, then the merge; seconds add up; the initial pair stays this model's."""
        self.stages += [{**st, "model": "merged"} for st in later.stages]
        self.stages.append({"stage": "merge", **numbers, "seconds": round(seconds, 3)})
        for kind, sec in later.seconds.items():
            self.seconds[kind] = self.seconds.get(kind, 0.0) + sec
        self.seconds["merge"] = self.seconds.get("merge", 0.0) + seconds
        self.reasons.update(later.reasons)
        self.say(f"merged with an earlier model: {numbers['shared_images']} shared images, {numbers['inliers']}/"
                 f"{numbers['common_points']} common points agree, {len(numbers['images_added'])} image(s) added")
        return self

    # --- the model's report -----------------------------------------------------------------------------

    def model_report(self, rec, camera: dict) -> dict:
        """The ``report`` of the model ``rec`` (:class:`~course_lib.sfm.reconstruction.Reconstruction`).

        Keys: ``initial_pair``, ``stages``, ``seconds``, ``camera`` (``camera``: the model and
        intrinsics the mapper used) and ``final`` (registered images, points, observations, track
        length, reprojection errors); :func:`~course_lib.sfm.pipeline.run_sfm` adds ``left_out``
        and the keys shared by all models once every model exists.
        """
        stats = rec.error_stats()
        initial = {**self.initial, "candidates": self.candidates}
        if self.relaxations:
            initial["relaxed"] = self.relaxations
        registered = {i for i in range(len(self.names)) if rec.registered[i]}
        self.reasons = {i: why for i, why in self.reasons.items() if i not in registered}
        return {"initial_pair": initial, "stages": self.stages, "seconds": dict(self.seconds),
                "camera": camera, "final": {
                    "registered_images": rec.n_registered,
                    "registered": [self.names[i] for i in range(len(self.names)) if rec.registered[i]],
                    "points": rec.n_points,
                    "observations": int(rec.inlier.sum()),
                    "mean_track_length": round(float(rec.inlier.sum() / max(rec.n_points, 1)), 3),
                    "mean_reprojection_error_px": round(stats["mean"], 4),
                    "median_reprojection_error_px": round(stats["median"], 4),
                    "rms_reprojection_error_px": round(stats["rms"], 4),
                    "max_reprojection_error_px": round(stats["max"], 4),
                }}
