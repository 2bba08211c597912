"""Tests of course_lib.viz: 3-D scene geometry and size, 2-D figures, widgets (headless)."""

from __future__ import annotations

import os
import re

os.environ.setdefault("MPLBACKEND", "Agg")

import numpy as np
import plotly.graph_objects as go
import pytest
from matplotlib.figure import Figure

import course_lib.viz as viz
from course_lib.data.synthetic import look_at, make_scene
from course_lib.validate import KitInputError
from course_lib.viz import figures, scene3d, widgets

K = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
SIZE = (640, 480)


@pytest.fixture(scope="module")
def scene():
    return make_scene(np.random.default_rng(0), n_cameras=5, n_points=5000)


def _xyz(trace) -> np.ndarray:
    return np.c_[np.asarray(trace.x, float), np.asarray(trace.y, float), np.asarray(trace.z, float)]


def _by_uid(fig, part: str):
    return [tr for tr in fig.data if part in tr.uid]


# ----------------------------------------------------------------------------- scene3d
def test_renderer_is_mimetype_unless_user_chose():
    import plotly.io as pio

    if not os.environ.get("PLOTLY_RENDERER"):
        assert pio.renderers.default == "plotly_mimetype"


def test_frustum_apex_far_plane_and_up_marker():
    C = np.array([1.0, -2.0, 3.0])
    R, t = look_at(C, np.array([4.0, 0.0, 10.0]))
    f = viz.camera_frustum(R, t, K, SIZE, scale=0.5)
    np.testing.assert_allclose(f["apex"], C, atol=1e-12)
    cam = (f["corners"] - C) @ R.T  # camera coordinates of the far rectangle
    np.testing.assert_allclose(cam[:, 2], 0.5, atol=1e-12)  # in front, at depth `scale`
    # corners: top-left, top-right, bottom-right, bottom-left (x right, y down)
    assert cam[0, 0] < cam[1, 0] and cam[0, 1] < cam[3, 1] and cam[2, 0] > cam[3, 0]
    # the corners project back to the image corners
    uv = (cam @ K.T)[:, :2] / 0.5
    np.testing.assert_allclose(uv, [[-0.5, -0.5], [639.5, -0.5], [639.5, 479.5], [-0.5, 479.5]], atol=1e-9)
    # the up marker sits above the top edge, i.e. towards camera -y (image top)
    top_mid = 0.5 * (f["corners"][0] + f["corners"][1])
    d = f["up_tip"] - top_mid
    up_world = R.T @ np.array([0.0, -1.0, 0.0])
    assert np.dot(d, up_world) / np.linalg.norm(d) > 0.99


def test_identity_camera_in_figure():
    fig = viz.scene_figure([(np.eye(3), np.zeros(3), K, SIZE, "ref")], camera_scale=2.0)
    (centres,) = _by_uid(fig, "centres")
    np.testing.assert_allclose(_xyz(centres), [[0.0, 0.0, 0.0]])
    assert list(centres.hovertext) == ["ref"]
    (fr,) = _by_uid(fig, "frustums")
    P = _xyz(fr)
    P = P[np.isfinite(P).all(1)]
    assert np.isclose(P[:, 2].max(), 2.0)  # far plane at z = +scale (in front, OpenCV)
    assert P[:, 2].min() == 0.0  # the apex
    assert P[:, 1].min() < -2.0 * 239.5 / 500.0 - 1e-3  # up marker above the top edge (-y)
    assert fig.layout.scene.aspectmode == "data"
    assert (fig.layout.scene.camera.up.x, fig.layout.scene.camera.up.y, fig.layout.scene.camera.up.z) == (0, -1, 0)


def test_default_scale_is_5_percent_of_scene(scene):
    fig = viz.scene_figure(points=scene.X)
    viz.add_cameras(fig, scene.R_cw, scene.t_cw, scene.K, scene.image_size)
    (fr,) = _by_uid(fig, "frustums")
    P = _xyz(fr)
    P = P[np.isfinite(P).all(1)]
    depth = (P[1] - scene.centers[0]) @ scene.R_cw[0].T  # first far corner of camera 0
    size = viz.scene_size(np.r_[scene.X, scene.centers])
    assert np.isclose(depth[2], 0.05 * size, rtol=1e-3)


def test_figure_json_is_deterministic_and_small(scene):
    rgb = np.random.default_rng(1).integers(0, 256, (5000, 3), dtype=np.uint8)  # worst case colours

    def build():
        cams = [(scene.R_cw[i], scene.t_cw[i], scene.K, scene.image_size, f"img{i}") for i in range(5)]
        fig = viz.scene_figure(cams, (scene.X, rgb), title="test")
        viz.add_cameras(fig, scene.R_cw, scene.t_cw + 0.1, scene.K, scene.image_size, legend_group="after BA")
        return fig.to_json()

    a, b = build(), build()
    assert a == b
    assert len(a) < 200_000, len(a)


def test_legend_groups_and_uids(scene):
    fig = viz.scene_figure()
    viz.add_cameras(fig, scene.R_cw, scene.t_cw, scene.K, scene.image_size, legend_group="before BA")
    viz.add_cameras(fig, scene.R_cw, scene.t_cw, scene.K, scene.image_size, legend_group="after BA")
    groups = [tr.legendgroup for tr in fig.data]
    assert groups == ["before BA"] * 2 + ["after BA"] * 2
    uids = [tr.uid for tr in fig.data]
    assert len(set(uids)) == len(uids)
    assert fig.data[0].line.color != fig.data[2].line.color  # one colour per group


def test_point_colours_survive(scene):
    rgb = np.zeros((5000, 3), np.uint8)
    rgb[:2500] = (250, 10, 10)
    rgb[2500:] = (10, 10, 250)
    fig = viz.add_points(viz.scene_figure(), scene.X, rgb, max_points=None)
    m = fig.data[0].marker
    idx = np.asarray(m.color)
    cols = [m.colorscale[int(i)][1] for i in idx[[0, -1]]]
    assert [tuple(int(c[k : k + 2], 16) for k in (1, 3, 5)) for c in cols] == [(255, 8, 8), (8, 8, 255)]


def test_subsampling_respects_budget(scene):
    fig = viz.scene_figure(points=scene.X, point_budget=1000)
    P = _xyz(fig.data[0])
    assert P.shape == (1000, 3)
    # the subset is made of input points (up to rounding) and is the same every time
    d = np.abs(P[:, None, :] - scene.X[None, :, :].astype(np.float32)).max(-1).min(1)
    assert d.max() < 1e-3
    P2 = _xyz(viz.scene_figure(points=scene.X, point_budget=1000).data[0])
    np.testing.assert_array_equal(P, P2)
    assert _xyz(viz.scene_figure(points=scene.X[:500], point_budget=1000).data[0]).shape == (500, 3)


def test_nan_points_are_dropped():
    X = np.arange(30, dtype=float).reshape(10, 3)
    X[[2, 5], 1] = np.nan
    X[7, 0] = np.inf
    rgb = np.tile(np.array([[1, 2, 3]], np.uint8), (10, 1))
    fig = viz.add_points(viz.scene_figure(), X, rgb)
    P = _xyz(fig.data[0])
    np.testing.assert_allclose(P, X[[0, 1, 3, 4, 6, 8, 9]])
    assert "(7)" in fig.data[0].name


def test_shape_errors_are_clear():
    fig = viz.scene_figure()
    with pytest.raises(KitInputError, match="transpose"):
        viz.add_points(fig, np.zeros((3, 10)))
    with pytest.raises(KitInputError, match="t_cw"):
        viz.add_cameras(fig, np.stack([np.eye(3)] * 2), np.zeros((3, 3)), K, SIZE)
    with pytest.raises(KitInputError, match="det = -1"):
        viz.add_cameras(fig, -np.eye(3), np.zeros(3), K, SIZE)
    with pytest.raises(KitInputError, match="image_size"):
        viz.add_cameras(fig, np.eye(3), np.zeros(3), K, 640)
    with pytest.raises(KitInputError, match="rgb"):
        viz.add_points(fig, np.zeros((4, 3)), np.zeros((3, 3), np.uint8))
    with pytest.raises(KitInputError, match="cameras\\[0\\]"):
        viz.scene_figure(cameras=[(np.eye(3), np.zeros(3))])


def test_rays_and_samples():
    o = np.zeros((10, 3))
    d = np.c_[np.linspace(-0.5, 0.5, 10), np.zeros(10), np.ones(10)]
    z = np.linspace(2.0, 6.0, 8)
    samples = o[:, None] + z[None, :, None] * d[:, None]
    w = np.random.default_rng(0).random((10, 8))
    fig = viz.add_rays(viz.scene_figure(up=(0, 0, 1)), o, d, samples, sample_values=w)
    rays, smp = fig.data
    P = _xyz(rays)
    P = P[np.isfinite(P).all(1)]
    assert P.shape == (20, 3) and np.isclose(P[:, 2].max(), 6.0)  # segments end at the farthest sample
    assert _xyz(smp).shape == (80, 3)
    fig = viz.add_rays(viz.scene_figure(), np.zeros((4, 4, 3)), np.ones((4, 4, 3)), max_rays=5)
    assert "(5)" in fig.data[0].name


def test_image_on_far_plane(scene):
    img = np.random.default_rng(0).integers(0, 255, (60, 80, 3), dtype=np.uint8)
    fig = viz.scene_figure()
    viz.add_cameras(fig, scene.R_cw[:2], scene.t_cw[:2], scene.K, scene.image_size, images=[img, img])
    meshes = [tr for tr in fig.data if isinstance(tr, go.Mesh3d)]
    assert len(meshes) == 2


def test_write_html_embeds_plotly_js(tmp_path, scene):
    fig = viz.scene_figure(points=scene.X[:100])
    p = viz.write_html(fig, tmp_path / "sub" / "scene.html")
    text = p.read_text(encoding="utf-8")
    assert p.stat().st_size > 1_000_000  # plotly.js itself is inside
    assert not re.search(r"<script[^>]*src=[\"']https?:", text)  # nothing fetched from a CDN
    assert "Plotly.newPlot" in text or "Plotly.react" in text
    assert 'id="course-lib-figure"' in text


# ----------------------------------------------------------------------------- figures
@pytest.fixture(scope="module")
def pair(scene):
    x1, x2, inl, _ = scene.pair(0, 1)
    return x1, x2, inl


def test_matplotlib_helpers_return_figures(scene, pair):
    import scipy.sparse as sp

    from course_lib.conventions import skew

    x1, x2, inl = pair
    img = np.random.default_rng(0).integers(0, 255, (150, 200, 3), dtype=np.uint8)
    # F from the true poses: x2^T F x1 = 0
    R = scene.R_cw[1] @ scene.R_cw[0].T
    t = scene.t_cw[1] - R @ scene.t_cw[0]
    Kinv = np.linalg.inv(scene.K)
    F = Kinv.T @ skew(t) @ R @ Kinv
    rng = np.random.default_rng(0)
    figs = [
        viz.draw_matches(img, img, x1, x2, inl, max_lines=50),
        viz.draw_matches(img[..., 0], img.astype(float) / 255, x1, x2),
        viz.draw_epipolar_lines(img, img, F, x1[inl], x2[inl], n=5),
        viz.plot_reprojection_errors(rng.random(100) * 3, rng.random(80)),
        viz.plot_reprojection_errors([rng.random(10), rng.random(10), np.array([np.nan, 1.0])], labels=["a", "b", "c"]),
        viz.plot_visibility(scene.visible, camera_names=[f"im{i}" for i in range(5)], sort_tracks=True),
        viz.plot_jacobian_sparsity(sp.random(300, 60, density=0.05, random_state=0, format="csr"), col_splits=[30]),
        viz.plot_jacobian_sparsity(np.eye(20)),
        viz.plot_jacobian_sparsity(sp.random(2000, 500, density=0.01, random_state=0), max_markers=1000),
        viz.plot_training_curves({"iterations": np.arange(50), "loss": np.exp(-np.arange(50) / 10), "psnr": np.arange(50) / 2.0,
                                  "test_psnr": [10.0, 20.0], "test_iterations": [24, 49]}),
        viz.plot_training_curves({"loss": [1.0, 0.5, 0.2]}),
        viz.image_grid(rng.random((5, 16, 16, 3)), titles=list("abcde"), ncols=3),
        viz.image_grid([img, img[:100, :50, 0]]),
    ]
    for f in figs:
        assert isinstance(f, Figure)
        assert f.dpi == figures.STYLE["figure.dpi"]
    png = figs[3]._repr_png_()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) < 100_000


def test_epipolar_points_on_their_lines(scene, pair):
    from course_lib.conventions import skew

    x1, x2, inl = pair
    R = scene.R_cw[1] @ scene.R_cw[0].T
    t = scene.t_cw[1] - R @ scene.t_cw[0]
    Kinv = np.linalg.inv(scene.K)
    F = Kinv.T @ skew(t) @ R @ Kinv
    img = np.zeros((600, 800, 3), np.uint8)
    fig = viz.draw_epipolar_lines(img, img, F, x1[inl], x2[inl], n=4)
    ax2 = fig.axes[1]
    lines = [ln for ln in ax2.get_lines() if len(ln.get_xdata()) == 2]
    pts = [ln for ln in ax2.get_lines() if len(ln.get_xdata()) == 1]
    for ln, pt in zip(lines, pts):
        (u0, u1), (v0, v1) = ln.get_xdata(), ln.get_ydata()
        pu, pv = pt.get_xdata()[0], pt.get_ydata()[0]
        dist = abs((u1 - u0) * (v0 - pv) - (u0 - pu) * (v1 - v0)) / np.hypot(u1 - u0, v1 - v0)
        assert dist < 5.0  # noise 0.5 px


def test_figure_input_errors(pair):
    x1, x2, inl = pair
    img = np.zeros((60, 80, 3), np.uint8)
    with pytest.raises(KitInputError, match="inliers"):
        viz.draw_matches(img, img, x1, x2, inl[:-1])
    with pytest.raises(KitInputError, match="rows"):
        viz.draw_matches(img, img, x1, x2[:-1])
    with pytest.raises(KitInputError, match="channels last"):
        viz.image_grid([np.zeros((3, 20, 20))])
    with pytest.raises(KitInputError, match="loss"):
        viz.plot_training_curves({"psnr": [1, 2]})
    with pytest.raises(KitInputError, match="V has shape"):
        viz.plot_visibility(np.zeros(5, bool))


# ----------------------------------------------------------------------------- widgets
def test_ransac_widget_reruns(scene, pair):
    from types import SimpleNamespace

    x1, x2, _ = pair
    calls = []

    def fake_ransac(a, b, rng, threshold_px):
        calls.append(threshold_px)
        r = np.hypot(*(a - a.mean(0)).T)
        return SimpleNamespace(inliers=r < 100 * threshold_px, n_iters=7)

    img = np.zeros((150, 200, 3), np.uint8)
    w = viz.ransac_threshold_widget(img, img, x1, x2, fake_ransac, thresholds=(0.5, 1.0, 2.0))
    slider, label, out = w.children
    first_label, first_out = label.value, out.outputs
    assert "image/png" in first_out[0]["data"]
    slider.value = 2.0
    assert calls == [1.0, 2.0]
    assert label.value != first_label and out.outputs != first_out
    slider.value = 1.0  # cached: no new run
    assert calls == [1.0, 2.0] and label.value == first_label


def test_ba_widget_redraws(scene):
    states = [(scene.R_cw, scene.t_cw + 0.05 * k, scene.X[:300] * (1 + 0.01 * k)) for k in range(3)]
    w = viz.ba_iterations_widget(states, scene.K, scene.image_size, costs=[9.0, 4.0, 1.0],
                                 reference=(scene.R_cw, scene.t_cw, scene.X[:300]))
    slider, label, out = w.children
    before = out.outputs
    assert "application/vnd.plotly.v1+json" in before[0]["data"]
    slider.value = 2
    assert out.outputs != before and "cost 1" in label.value
    with pytest.raises(KitInputError, match="costs"):
        viz.ba_iterations_widget(states, scene.K, scene.image_size, costs=[1.0])


def test_nerf_snapshot_slider(tmp_path):
    import imageio.v3 as iio

    imgs = np.random.default_rng(0).random((3, 8, 8, 3))
    p = tmp_path / "snap.png"
    iio.imwrite(p, (imgs[0] * 255).astype(np.uint8))
    w = viz.nerf_snapshot_slider([p, imgs[1], imgs[2]], iterations=[100, 200, 300], reference=imgs[0])
    slider, label, row = w.children
    assert "300" in label.value
    slider.value = 0
    assert "100" in label.value
    assert row.children[0].children[1].value == p.read_bytes()


def test_novel_view_widget():
    seen = []

    def render(az, el):
        seen.append((az, el))
        return np.full((8, 8, 3), (az + 180.0) / 360.0)

    w = viz.novel_view_widget(render, initial=(0.0, 10.0))
    (az, el), label, view = w.children[0].children, w.children[1], w.children[2]
    first = view.value
    az.value = 90.0
    el.value = 20.0
    assert seen == [(0.0, 10.0), (90.0, 10.0), (90.0, 20.0)]
    assert view.value != first and "azimuth 90" in label.value
    with pytest.raises(KitInputError, match="render_fn"):
        viz.novel_view_widget(None)


def test_modules_document_their_api():
    for mod, names in ((scene3d, scene3d.__all__), (figures, figures.__all__), (widgets, widgets.__all__)):
        for n in names:
            obj = getattr(mod, n)
            if callable(obj) and not isinstance(obj, type):
                assert f"{n}(" in mod.__doc__, f"{mod.__name__} docstring does not list {n}"
