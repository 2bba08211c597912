"""Registration of the next image (course_lib.sfm.registration): PnP tried again where its pose fits unusually badly."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from course_lib.conventions import rotation_angle_deg
from course_lib.data.synthetic import look_at
from course_lib.sfm.mapper_options import MapperOptions
from course_lib.sfm.registration import ImageRegistration


class _Registration(ImageRegistration):
    """Only what the retry reads: the camera, the options, the draws and the earlier registrations' median errors."""

    def __init__(self, K, medians, **options):
        self.K, self.opts, self.rng, self.pnp_medians = K, MapperOptions(**options), np.random.default_rng(0), list(medians)


def _view(seed=0, n=150, noise_px=0.3):
    """A narrow view (f = 2000 px, 640x480) of points in a box 20 units away: ``K, R, t, X (n, 3), uv (n, 2)``."""
    rng = np.random.default_rng(seed)
    K = np.array([[2000.0, 0, 319.5], [0, 2000.0, 239.5], [0, 0, 1]])
    R, t = look_at(np.array([0.0, -20.0, 1.0]), np.zeros(3), up=(0.0, 0.0, 1.0))
    X = rng.uniform(-1, 1, (n, 3))
    x = X @ R.T + t
    uv = x[:, :2] / x[:, 2:] * 2000.0 + [319.5, 239.5] + rng.normal(0, noise_px, (n, 2))
    return K, R, t, X, uv


def _orbit(R, t, centre, deg):
    """The camera turned ``deg`` about its own x axis through ``centre``: the centre stays in the middle of the view."""
    G = Rotation.from_rotvec(np.radians(deg) * R[0]).as_matrix()
    C = centre + G @ (-R.T @ t - centre)
    R2 = R @ G.T
    return R2, -R2 @ C


def test_a_pose_that_fits_unusually_badly_is_found_again():
    K, R, t, X, uv = _view()
    Rw, tw = _orbit(R, t, X.mean(0), 3.0)  # the wrong pose: each inlier a few pixels off
    reg = _Registration(K, [0.4, 0.5, 0.45])
    R2, t2, inl, info = reg._retry_if_unusual(X, uv, np.ones(len(X), bool), Rw, tw)
    assert rotation_angle_deg(R2, R) < 0.2
    assert info["pnp_retries"] >= 1 and info["retry_turn_deg"] == pytest.approx(3.0, abs=0.3)
    assert inl.all()


@pytest.mark.parametrize("medians, options", [([0.4, 0.5, 0.45], {}), ([0.4, 0.5], {}), ([0.4, 0.5, 0.45], {"pnp_retries": 0})],
                         ids=["usual", "too-few-registrations-to-tell", "turned-off"])
def test_a_usual_pose_is_kept_as_it_is(medians, options):
    K, R, t, X, uv = _view()
    reg = _Registration(K, medians, **options)
    start = (R, t) if not options and len(medians) >= 3 else _orbit(R, t, X.mean(0), 3.0)
    R2, t2, inl, info = reg._retry_if_unusual(X, uv, np.ones(len(X), bool), *start)
    assert info == {} and R2 is start[0] and t2 is start[1]
