"""Curved objects with render-based edges (issue #13): the synthetic colouring of curved meshes, the contour
side test that keeps background texture edges off a silhouette, and `mst synth orbit|fast` sequences of a
torus, a blob and a vase tracked edges-only and with the SLAM aid against the issue's 0.3 % / 0.3 deg."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("open3d")


def test_curved_mesh_coloured_per_smooth_patch():
    """A closed curved mesh is coloured per smooth patch (a vase: body + two caps), not per triangle; a
    polyhedral box TIN and an open terrain TIN keep their per-plane groups (their renders are unchanged)."""
    from mst.meshtools.generate import blob, box, terrain, torus, vase
    from mst.pipeline.synth.scene import plane_ids, smooth_patch_ids

    for V, F, patches in ((*vase(), 3), (*torus(), 1), (*blob(), 1)):
        assert smooth_patch_ids(V, F, plane_ids(V, F)).max() + 1 == patches
    for V, F in (box((0.3, 0.2, 0.1), split=5), terrain(cells=30)[:2]):
        p = plane_ids(V, F)
        assert np.array_equal(smooth_patch_ids(V, F, p), p)


def _disc_image(r_px=40.0, obj=100.0, bg=180.0, stripe=60.0, stripe_at=4.5, size=160):
    """A disc (object gray ``obj``) of radius ``r_px`` on a background ``bg`` with a dark ring (``stripe``)
    from ``r + stripe_at`` outward: a background texture edge ``stripe_at`` px outside the silhouette.
    Anti-aliased by 4x4 supersampling."""
    import cv2

    s = 4
    c = (size * s - 1) / 2.0
    yy, xx = np.mgrid[0:size * s, 0:size * s]
    rr = np.hypot(xx - c, yy - c) / s
    img = np.where(rr < r_px, obj, np.where(rr < r_px + stripe_at, bg, stripe)).astype(np.float32)
    return np.clip(np.rint(cv2.resize(img, (size, size), interpolation=cv2.INTER_AREA)), 0, 255).astype(np.uint8)


def test_contour_side_test_rejects_background_edge():
    """Silhouette samples of a disc with a background texture edge 4.5 px outside: the candidate on the true
    contour keeps its object side (gray 100 inside, as in the reference frame) and is kept; the one on the
    background edge has background (180) on its inner side, 80 gray levels from the reference's 100 while
    the tolerance is max(0.5 x 80, 6) = 40: rejected. Without the stripe both candidates would be the same
    edge; here the test is decided by the image, not by the distance."""
    from mst.pipeline.tracking.render_edges import contour_side_test

    img = _disc_image()
    size, r = img.shape[0], 40.0
    c = (size - 1) / 2.0
    a = np.linspace(0, 2 * np.pi, 48, endpoint=False)
    n_out = np.stack([np.cos(a), np.sin(a)], 1)
    uv = c + r * n_out
    K = np.array([[100.0, 0, c], [0, 100.0, c], [0, 0, 1]])
    X = np.column_stack([(uv - c) / 100.0, np.ones(len(uv))])  # camera = model frame, z = 1 m: projects onto uv
    offset = np.column_stack([np.zeros(len(uv)), np.full(len(uv), 4.5)])  # along n_out: true edge, stripe edge
    ok = contour_side_test(img, K, uv, n_out, X, offset, n_out, img, np.eye(4))
    assert ok[:, 0].all() and not ok[:, 1].any()


def _ramp_disc(rim: float, bg: float, slope: float = 6.0, r: float = 40.0, size: int = 160) -> np.ndarray:
    """A disc of radius ``r`` px whose gray level rises by ``slope`` per px from ``rim`` at its contour over 6 px
    inward (a smooth object's shading ramp: darker toward its rim), on a uniform background ``bg``; 4x4 anti-aliased."""
    import cv2

    s = 4
    c = (size - 1) / 2.0
    yy, xx = np.mgrid[0:size * s, 0:size * s]
    rr = np.hypot((xx + 0.5) / s - 0.5 - c, (yy + 0.5) / s - 0.5 - c)
    hi = np.where(rr < r, rim + slope * np.minimum(r - rr, 6.0), bg).astype(np.float32)
    return np.clip(np.rint(cv2.resize(hi, (size, size), interpolation=cv2.INTER_AREA)), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("rim,bg,bias_sign", [(120.0, 90.0, -1.0), (60.0, 95.0, 1.0)])
def test_rim_crossing_removes_the_shading_ramp_bias(rim, bg, bias_sign):
    """Silhouette of a disc that darkens toward its rim (6 gray levels per px), brighter (120 -> 156 inside, on 90)
    or darker (60 -> 96, on 95) than the background. The 3-px mask's peak (the moving-edge search) is pulled toward
    the ramp's bright side: inward on the bright disc, outward on the dark one, by more than 0.1 px on average.
    Moved onto the crossing with the middle of the step between the extrapolated object level and the background,
    candidates started on the contour or 0.6 px off it land within 0.08 px of it on average and at most half the
    peak's mean bias (budget: the bilinear profile of an oblique anti-aliased edge is off by up to ~0.15 px per
    sample, 0.11 px without a ramp; 4x4 supersampling quantises the edge to 1/32 px), every one within 0.25 px."""
    from mst.pipeline.tracking.moving_edges import search_edges
    from mst.pipeline.tracking.render_edges import crossing_offsets

    img = _ramp_disc(rim, bg)
    c, r = (img.shape[0] - 1) / 2.0, 40.0
    a = np.linspace(0, 2 * np.pi, 64, endpoint=False) + 0.01
    n_out = np.stack([np.cos(a), np.sin(a)], 1)
    uv = c + r * n_out
    m = search_edges(img, uv, n_out, None, search_range=4, threshold=10.0, mu1=0.5, mu2=0.5, size=3, n_masks=180,
                     n_candidates=1)
    sgn = np.sign((m.normal * n_out).sum(1))  # search normal -> outward
    peak = m.offset[:, 0] * sgn
    assert np.isfinite(peak).all() and bias_sign * peak.mean() > 0.1, peak.mean()
    for start in (0.0, 0.6, -0.6):
        moved = crossing_offsets(img, uv, n_out, np.full((len(uv), 1), start) * sgn[:, None], m.normal)[:, 0] * sgn
        assert np.isfinite(moved).all(), start
        assert abs(moved.mean()) <= min(0.08, 0.5 * abs(peak.mean())) and np.abs(moved).max() <= 0.25, (
            start, moved.mean(), np.abs(moved).max())


def test_body_of_revolution_symmetry_is_a_gauge():
    """The torus and the vase are found to be bodies of revolution about their z axis, the blob and a box are not.
    Their turn about the axis changes no image, so (1) two poses that differ by that turn compare equal
    (``align_to``: the camera centres coincide after it) and (2) the pose covariance does not count it as an
    uncertainty: along the turn's twist the gauge-fixed variance is < 1e-6 of the free one, and a direction
    orthogonal to it keeps its variance within 1 % (the information of the other directions is unchanged)."""
    from mst.core.camera import Camera
    from mst.core.poses import inv_T, look_at
    from mst.meshtools.generate import blob, box, torus, vase
    from mst.pipeline.tracking.render_edges import RenderEdgeProvider

    cam = Camera(300.0, 300.0, 159.5, 119.5, 320, 240)
    provs = {name: RenderEdgeProvider(*f(), cam) for name, f in (("torus", torus), ("vase", vase), ("blob", lambda: blob(subdivisions=3)),
                                                                  ("box", lambda: box((0.3, 0.2, 0.1), split=5)))}
    for name in ("torus", "vase"):
        a, _ = provs[name].axis
        assert abs(abs(a[2]) - 1.0) < 1e-6, (name, a)
    assert provs["blob"].axis is None and provs["box"].axis is None
    p = provs["vase"]
    T1 = inv_T(look_at(np.array([0.6, 0.1, 0.3]), np.array([0.0, 0.0, 0.1]), (0, 0, 1)))
    T2 = inv_T(look_at(np.array([0.1, 0.6, 0.3]), np.array([0.0, 0.0, 0.1]), (0, 0, 1)))
    c = lambda T: -T[:3, :3].T @ T[:3, 3]  # noqa: E731
    assert np.linalg.norm(c(p.align_to(T1, T2)) - c(T1)) < 1e-9 and provs["blob"].align_to(T1, T2) is T2
    # an information matrix that cannot see the turn (its twist n in its null space) plus a full-rank rest
    a, q = p.axis
    w = T1[:3, :3] @ a
    n = np.concatenate([np.cross(T1[:3, :3] @ q + T1[:3, 3], w), w])
    n /= np.linalg.norm(n)
    rng = np.random.default_rng(0)
    B = rng.standard_normal((6, 6))
    B -= np.outer(B @ n, n)
    W = B.T @ B + 1e-9 * np.outer(n, n)
    cov = np.linalg.inv(W)
    cg = p.gauge_cov(T1, W, cov, 1.0)
    u = np.linalg.svd(B)[2][0]  # a direction the rest sees, orthogonal to n
    assert n @ cg @ n < 1e-6 * (n @ cov @ n)
    assert abs(u @ cg @ u / (u @ np.linalg.pinv(W) @ u) - 1.0) < 0.01
    assert provs["blob"].gauge_cov(T1, W, cov, 1.0) is cov


def test_silhouette_normals_point_out_of_the_object():
    """The edgelets' 2D normals of a sphere's silhouette point away from its centre (the side test reads the
    object at -normal), at the render pose and once reprojected by the provider at another pose."""
    import trimesh

    from mst.core.camera import Camera
    from mst.pipeline.tracking.render_edges import RenderEdgeProvider

    m = trimesh.creation.icosphere(subdivisions=4, radius=0.1)
    cam = Camera(300.0, 300.0, 159.5, 119.5, 320, 240)
    p = RenderEdgeProvider(np.asarray(m.vertices), np.asarray(m.faces), cam)
    for dx in (0.0, 0.02):
        T = np.eye(4)
        T[:3, 3] = [dx, 0.0, 0.5]
        S = p.samples(T, cam.K, 320, 240)
        c = cam.K[:2, 2] + 300.0 * np.array([dx, 0.0]) / 0.5
        radial = (S.uv - c) / np.linalg.norm(S.uv - c, axis=1, keepdims=True)
        assert len(S) > 50 and ((radial * S.normal).sum(1) > 0.9).all()


# ---------------------------------------------------------------------------------------------- sequences
def _mesh(name):
    from mst.meshtools.generate import blob, torus, vase

    return {"torus": torus, "blob": blob, "vase": vase}[name]()


def _run(tmp_path, mst, shape, scenario, slam):
    import json

    from mst.core.trajectory import read_tum
    from mst.meshtools.formats import save_triangles
    from mst.pipeline import synth

    V, F = _mesh(shape)
    save_triangles(tmp_path / f"{shape}.obj", V, F)
    d = tmp_path / "seq"
    s = synth.synthesize(scenario, tmp_path / f"{shape}.obj", d, synth.SynthConfig(
        frames=16, width=640, height=480, depth=False, aa_samples=4, texture_size=256))
    out = tmp_path / "traj.txt"
    r = mst("track", d / "rgb", "--model", d / "model.obj", "--camera", d / "camera.json", "--init",
            d / "cMo" / "000000.txt", "-o", out, "--fps", "30", "--slam", slam, "--json")
    js = json.loads(r.stdout)
    return js, read_tum(out)[1], read_tum(d / "gt.txt")[1], s["distance_m"]


def _errors(shape, est, gt):
    from test_track_render import _error_modulo_z_symmetry

    from mst.core.poses import pose_error

    # the torus and the vase turn about their z axis unseen (bodies of revolution): compared modulo that turn
    return pose_error(est, gt) if shape == "blob" else _error_modulo_z_symmetry(est, gt)


# measured (640x480, 16 frames): mean % of distance / deg; the cases not yet at the 0.3 % / 0.3 deg are
# strict xfails, so that they are reported as soon as they pass. The edgelets lie on the rendered mesh's contour to
# 1/256 px (the facet sagitta of these meshes is ~0.01 px, so a smooth n.v = 0 rim would not move them); the image
# side limits. Rims are located on the crossing with the object's shading ramp (render_edges.crossing_offsets;
# before it: vase 0.34 / 0.35 %, blob fast 1.1 %, which were xfails here too)
_NOT_MET = {
    ("vase", "orbit", "off"): "0.303 % / 0.20 deg mean (the target 0.3 %): the vase's orbit is at the target, not within it. "
                              "Its mean error over 16 frames is noise-limited (frame 0, fitted from the TRUE pose, is "
                              "0.6 % off: its bright left side on a bright textured floor leaves 141 of 242 samples "
                              "inliers), and it had passed at 0.288 % under OpenBLAS's SkylakeX kernels, whose last bit "
                              "in the synthetic initial pose (1 ulp of one rotation element) sent the fit another way. "
                              "Since session 22 every CPU runs the same kernels (mst.cpu), so this is the one result "
                              "everywhere. A full-resolution render gives 0.24 % here but costs the torus fast and blob "
                              "orbit accuracy and 10-75 % more time on fast motion (not taken)",
    ("vase", "orbit", "auto"): "as edges only (the aid stays on standby): 0.303 % mean against the 0.3 % target",
    ("blob", "fast", "off"): "3 of 16 frames output, and the refusals are right: frames 3-9 are refused by the error "
                             "budget as 'pose uncertain' (2 sigma 1.2-2.1 % of the distance) and, with the budget "
                             "lifted, are 0.24-2.28 % off (frames 4-8 0.9-2.3 %); frames 10-15 (2 sigma 0.6-0.7 %) stay "
                             "refused by the return hysteresis (0.5 x the budget). Cause: 8 deg per frame views with "
                             "too little contour (at the true pose of frame 6 only 150 of 234 silhouette samples find "
                             "a moving edge: bright side on a bright textured floor); all 16 frames: 0.70 % / 0.40 deg "
                             "mean (session 6)",
    ("blob", "fast", "auto"): "3 of 16 frames output on the session-7 tree (the same refusals; the aid does not help an "
                              "untextured object). At the TRUE poses of frames 3-6 the fit's own 2 sigma is 1.1-1.8 % "
                              "(> the 1 % budget): the silhouette alone leaves lateral translation + rotation weak "
                              "(1-sigma 5-7 mm), an information limit of the contour, not of the start",
}
_CASES = [pytest.param(sh, sc, sl, marks=[pytest.mark.slow] + ([pytest.mark.xfail(reason=_NOT_MET[(sh, sc, sl)],
                                                                                  strict=True)]
                                                               if (sh, sc, sl) in _NOT_MET else []))
          for sh in ("torus", "blob", "vase") for sc in ("orbit", "fast") for sl in ("off", "auto")]


@pytest.mark.parametrize("shape,scenario,slam", _CASES)
def test_synth_curved_tracked(tmp_path, mst, shape, scenario, slam):
    """`mst synth orbit|fast` of a torus (9,216 triangles), a blob (20,480, concavities) and a vase (12,288),
    640x480, 16 frames, `--edges auto` (render) from the true first pose, edges only (`--slam off`) and with
    the default aid: every frame tracked, mean translation error <= 0.3 % of the camera distance and mean
    rotation error <= 0.3 deg (issue #13's targets; budget: 0.3 % of 1 m = 3 mm = 1.6 px of depth-induced
    contour scale on a 300-px object, i.e. about 0.1 px of mean contour error)."""
    js, est, gt, dist = _run(tmp_path, mst, shape, scenario, slam)
    assert js["edges"] == "render"
    assert js["tracked"] == 16, js["tracked"]
    dt, dr = _errors(shape, est, gt)
    assert dt.mean() <= 0.003 * dist and dr.mean() <= 0.3, (dt.mean() / dist, dr.mean())
