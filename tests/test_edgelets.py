"""Edgelet extraction from CPU renders (mst.pipeline.tracking.edgelets): shapes, units, geometry on a sphere,
a box and a torus; even and stable sampling; the --edges auto rule; render-edge samples for the tracker."""

from __future__ import annotations

import numpy as np
import pytest

from mst.core.poses import inv_T, look_at

pytest.importorskip("open3d")

W, H = 320, 240
K = np.array([[300.0, 0, 159.5], [0, 300.0, 119.5], [0, 0, 1]])


def _renderer(V, F):
    from mst.pipeline.render import Renderer

    return Renderer(np.asarray(V, float), np.asarray(F, np.int64))


def _icosphere(radius=0.1, sub=4):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=sub, radius=radius)
    return np.asarray(m.vertices), np.asarray(m.faces)


def _T(eye, target=(0, 0, 0), up=(0, 0, 1)):
    return inv_T(look_at(np.asarray(eye, float), np.asarray(target, float), up))


def test_sphere_silhouette_subpixel():
    """Sphere r = 0.1 m at 0.5 m: every edgelet is a silhouette point on the sphere, its pixel on the
    projected circle and its 2D normal radial.

    Budget: the icosphere (subdivision 4, 5,120 faces) is inscribed in the sphere, its edge midpoints
    r (1 - cos(edge angle / 2)) ~ 0.05 % inside: 0.1 px on the 63-px circle; the bisection leaves
    1/256 of a half-resolution pixel. Bound 0.25 px (mean 0.15 px). Normals: exact image of the surface
    normal at a grazing hit, facets of ~4 deg: bound 5 deg.
    """
    from mst.pipeline.tracking.edgelets import SILHOUETTE, extract_edgelets

    V, F = _icosphere()
    r = _renderer(V, F)
    T = np.eye(4)
    T[2, 3] = 0.5
    e = extract_edgelets(r, T, K, W, H, scale=0.5, budget=200)
    assert 60 <= len(e) <= 200
    assert e.X_model.shape == (len(e), 3) and e.t_model.shape == (len(e), 3)
    assert e.uv_px.shape == (len(e), 2) and e.normal_px.shape == (len(e), 2) and e.depth_m.shape == (len(e),)
    assert (e.kind == SILHOUETTE).all()
    assert np.allclose(np.linalg.norm(e.t_model, axis=1), 1) and np.allclose(np.linalg.norm(e.normal_px, axis=1), 1)
    assert np.abs(np.linalg.norm(e.X_model, axis=1) - 0.1).max() < 1e-4  # on the surface (metres)
    c = K[:2, 2]
    rho_px = 300 * 0.1 / np.sqrt(0.5**2 - 0.1**2)
    d = np.linalg.norm(e.uv_px - c, axis=1)
    assert np.abs(d - rho_px).max() < 0.25 and np.abs(d - rho_px).mean() < 0.15
    radial = (e.uv_px - c) / d[:, None]
    ang = np.degrees(np.arccos(np.clip(np.abs((radial * e.normal_px).sum(1)), 0, 1)))
    assert ang.max() < 5.0
    # depth in metres: the silhouette circle lies at z = D - r^2 / D; along a grazing ray a point is only
    # fixed to within its facet (edges ~ 4 deg x 0.1 m = 7 mm long, so +-3.5 mm): 4 mm
    assert np.allclose(e.depth_m, 0.5 - 0.1**2 / 0.5, atol=4e-3)


def test_sampling_even_and_stable():
    """Buckets x 4 sectors: the budget is respected, the four orientation sectors of a circle are equally
    filled (within 2x), and a 0.2-deg turn of the view keeps most edgelets within 0.5 px of the old ones."""
    from mst.pipeline.tracking.edgelets import extract_edgelets

    V, F = _icosphere()
    r = _renderer(V, F)
    T0 = _T([0.5, 0.0, 0.05])
    for budget in (40, 120):
        e = extract_edgelets(r, T0, K, W, H, budget=budget)
        assert 0.5 * budget <= len(e) <= budget
    e0 = extract_edgelets(r, T0, K, W, H, budget=120)
    ang = np.degrees(np.arctan2(e0.normal_px[:, 1], e0.normal_px[:, 0])) % 180
    counts = np.bincount(np.minimum((ang // 45).astype(int), 3), minlength=4)
    assert counts.min() * 2 >= counts.max(), counts
    a = np.radians(0.2)
    e1 = extract_edgelets(r, _T([0.5 * np.cos(a), 0.5 * np.sin(a), 0.05]), K, W, H, budget=120)
    d = np.linalg.norm(e1.uv_px[:, None] - e0.uv_px[None], axis=2).min(1)
    assert (d < 0.5).mean() > 0.7


def test_box_creases_and_silhouette():
    """A box seen from a corner: crease edgelets lie on the box's edges with tangents along an axis,
    silhouette ones on its outline; all points on the surface (metres)."""
    from mst.meshtools.generate import box
    from mst.pipeline.tracking.edgelets import CREASE, SILHOUETTE, extract_edgelets

    V, F = box((0.2, 0.15, 0.1), split=3)
    V = V - [0.1, 0.075, 0.05]
    r = _renderer(V, F)
    e = extract_edgelets(r, _T([0.4, 0.3, 0.35]), K, W, H, budget=300)
    assert (e.kind == CREASE).sum() >= 20 and (e.kind == SILHOUETTE).sum() >= 20
    half = np.array([0.1, 0.075, 0.05])
    on_edge = (np.abs(np.abs(e.X_model) - half) < 1e-3).sum(1) >= 2  # two coordinates at a face: a box edge
    assert on_edge.mean() > 0.95
    cr = e.kind == CREASE
    axis_cos = np.abs(e.t_model[cr]).max(1)
    assert (axis_cos > np.cos(np.radians(2))).mean() > 0.95  # crease tangent = the edge direction
    assert np.abs(e.X_model).max() <= 0.1 + 1e-6


def test_torus_hole_contours():
    """A lying torus seen from above at 50 deg: contours outside and around the hole, every point on the
    torus surface ((sqrt(x^2 + y^2) - R)^2 + z^2 = r^2, within 0.05 % of R)."""
    from mst.meshtools.generate import torus
    from mst.pipeline.tracking.edgelets import extract_edgelets

    R, rr = 0.15, 0.05
    V, F = torus(R, rr, n_major=128, n_minor=64)
    V = V - [0, 0, rr]
    r = _renderer(V, F)
    e = extract_edgelets(r, _T([0.55, 0.0, 0.65]), K, W, H, budget=300)
    rho = np.hypot(e.X_model[:, 0], e.X_model[:, 1])
    dev = np.abs(np.hypot(rho - R, e.X_model[:, 2]) - rr)
    assert dev.max() < 5e-4 * R * 10 and np.median(dev) < 1e-3 * rr
    assert (rho < R).sum() >= 10 and (rho > R).sum() >= 20  # hole contour and outer contour


def test_nothing_in_view():
    from mst.pipeline.tracking.edgelets import extract_edgelets

    V, F = _icosphere()
    e = extract_edgelets(_renderer(V, F), _T([0.5, 0, 0], target=(1.0, 0, 0)), K, W, H)  # looking away
    assert len(e) == 0 and e.X_model.shape == (0, 3)


def test_edges_auto_rule(tmp_path):
    from mst.meshtools.generate import box, box_model, l_shape_model, torus
    from mst.meshtools.model import PolygonModel
    from mst.pipeline.tracking.render_edges import choose_edges, curved_fraction

    V, F = torus()
    assert curved_fraction(V, F) > 0.9
    Vb, Fb = box(split=8)
    assert curved_fraction(Vb, Fb) == 0.0
    assert choose_edges(PolygonModel(V, list(F)), "t.obj", "auto") == "render"
    assert choose_edges(PolygonModel(Vb, list(Fb)), "b.obj", "auto") == "polygon"  # 768 planar triangles
    Vb, Fb = box(split=10)
    assert choose_edges(PolygonModel(Vb, list(Fb)), "b.obj", "auto") == "render"  # a TIN: 1,200 triangles
    assert choose_edges(box_model(), "b.cao", "auto") == "polygon"
    Vl, Fl = l_shape_model().triangulate()
    assert choose_edges(PolygonModel(Vl, list(Fl)), "l.obj", "auto") == "polygon"  # small planar triangle file
    assert choose_edges(PolygonModel(V, list(F)), "t.wrl", "auto") == "polygon"
    assert choose_edges(PolygonModel(Vl, list(Fl)), "l.obj", "render") == "render"


def test_provider_samples_and_rerender_rule():
    """Samples for the tracker: one local line per edgelet through X; reprojection without a re-render for a
    small motion, a re-render once the camera centre moved by more than a_max * D."""
    from mst.core.camera import Camera
    from mst.pipeline.tracking.render_edges import RenderEdgeProvider

    V, F = _icosphere()
    cam = Camera(300.0, 300.0, 159.5, 119.5, W, H)
    p = RenderEdgeProvider(V, F, cam)
    T0 = _T([0.5, 0.0, 0.05])
    S = p.samples(T0, K, W, H)
    assert p.n_renders == 1 and len(S) > 30
    assert np.allclose(0.5 * (S.A_model + S.B_model), S.X_model)
    assert np.array_equal(S.edge, np.arange(len(S)))
    a_max = p.max_view_turn_rad(T0)
    assert np.radians(0.2) <= a_max <= np.radians(3.0)
    small = 0.3 * a_max
    p.samples(_T([0.5 * np.cos(small), 0.5 * np.sin(small), 0.05]), K, W, H)
    assert p.n_renders == 1
    big = 1.5 * a_max
    p.samples(_T([0.5 * np.cos(big), 0.5 * np.sin(big), 0.05]), K, W, H)
    assert p.n_renders == 2
    # pyramid level: the same edgelets projected with half-resolution intrinsics
    from mst.pipeline.tracking.edgelets import scaled_K

    S2 = p.samples(p.cache.T_cam_model, scaled_K(K, 0.5), W // 2, H // 2)
    assert p.n_renders == 2 and len(S2) > 0.8 * len(S)


def test_non_manifold_mesh_same_contours():
    """Non-manifold input (every triangle also present reversed, plus a fin: three triangles on one edge) gives
    the same edgelets as the clean torus: the render sees surfaces, not topology (within 0.05 px: the
    bisection's 1/256 px plus float32 ray casts)."""
    from mst.meshtools.generate import torus
    from mst.pipeline.tracking.edgelets import extract_edgelets

    V, F = torus(0.15, 0.05, n_major=96, n_minor=48)
    T = _T([0.55, 0.0, 0.45], target=(0, 0, 0.0))
    e0 = extract_edgelets(_renderer(V, F), T, K, W, H, budget=300)
    a, b = F[0, 0], F[0, 1]
    Vn = np.vstack([V, V[a] + [0.0, 0.0, 1e-4]])  # a zero-width fin inside the surface on edge (a, b)
    Fn = np.vstack([F, F[:, ::-1], [[a, b, len(V)]]])
    e1 = extract_edgelets(_renderer(Vn, Fn), T, K, W, H, budget=300)
    assert len(e1) == len(e0)
    d = np.linalg.norm(e1.uv_px[:, None] - e0.uv_px[None], axis=2).min(1)
    assert d.max() < 0.05
