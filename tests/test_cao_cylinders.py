"""ViSP ``.cao`` cylinders and circles: a user's ViSP model is tracked whole (issue #13: any model is a model).

A cylinder becomes a closed triangle surface (:mod:`mst.meshtools.solids`) that every triangle reader
returns (``mst synth``, ``c2m``, ``refine``), and ``mst track`` follows it with render-based edges: its
limbs (the contours ViSP tracks) and its end rims, where a ``.cao`` circle on that rim is the same curve.
Before, the cylinders and circles were read and silently dropped: a cylinder-only model could not be
tracked at all ("model has no faces").
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from mst import InputError
from mst.meshtools.formats import load_model, load_triangles, save_model
from mst.meshtools.model import PolygonModel
from mst.meshtools.solids import CYLINDER_SEGMENTS, circle_on_cylinder_end, cylinder_surface

R_M, H_M, BOX_M = 0.05, 0.2, 0.2  # cylinder radius and height, box side (a ViSP tutorial's cube and cylinder)


def _box_and_cylinder(path, box: bool = True):
    """A ``.cao``: a box (optional) with a cylinder standing on its top and a circle on the cylinder's top rim; without
    the box, the cylinder (a can) stands on the model's origin along its z axis."""
    from mst.meshtools.generate import box_model

    b = box_model((BOX_M, BOX_M, BOX_M))
    V0 = np.asarray(b.vertices, float) if box else np.zeros((0, 3))
    c0 = np.array([BOX_M / 2, BOX_M / 2, BOX_M]) if box else np.zeros(3)  # the can's axis: the model z axis
    c1 = c0 + [0.0, 0.0, H_M]
    n = len(V0)
    V = np.concatenate([V0, [c0, c1, c1 + [R_M, 0, 0], c1 + [0, R_M, 0]]])
    m = PolygonModel(V, list(b.faces) if box else [], names=list(b.names) if box else [],
                     cylinders=[{"p1": n, "p2": n + 1, "radius": R_M, "name": "cyl"}],
                     circles=[{"radius": R_M, "center": n + 1, "p1": n + 2, "p2": n + 3, "name": "top"}])
    save_model(path, m)
    return path


def _edges_of(F):
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    return np.unique(E, axis=0, return_counts=True)


def test_cylinder_surface_is_closed_outward_and_on_its_radius():
    p1, p2, r = np.array([0.3, -0.2, 1.0]), np.array([0.5, 0.4, 1.9]), 0.07  # an oblique axis
    V, F = cylinder_surface(p1, p2, r)
    n = CYLINDER_SEGMENTS
    assert F.shape == (4 * n, 3)
    _, counts = _edges_of(F)
    assert (counts == 2).all()  # closed and edge-manifold
    # divergence theorem: the enclosed volume is the inscribed prism's, positive (the normals point out)
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    vol = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
    h = np.linalg.norm(p2 - p1)
    assert vol == pytest.approx(0.5 * n * r * r * np.sin(2 * np.pi / n) * h, rel=1e-9)
    axis = (p2 - p1) / h
    t = (V - p1) @ axis
    radial = np.linalg.norm((V - p1) - t[:, None] * axis, axis=1)
    ring = radial > 0.5 * r  # the rest are the end discs' centres, on the axis
    assert ring.sum() == 2 * n and (~ring).sum() <= 2
    np.testing.assert_allclose(radial[ring], r, rtol=1e-12)
    np.testing.assert_allclose(radial[~ring], 0.0, atol=1e-12)
    assert np.allclose(np.minimum(np.abs(t), np.abs(t - h)), 0.0, atol=1e-12)  # all in the two end planes
    with pytest.raises(ValueError):
        cylinder_surface(p1, p1, r)


def test_every_triangle_reader_sees_the_cylinder(tmp_path, mst):
    """``load_triangles`` returns the cylinder's surface (``primitives=False``: the faces only), and C2M of points
    on the true cylinder against the model is within the tessellation's sagitta ``r (1 - cos(pi / n))``."""
    cao = _box_and_cylinder(tmp_path / "cc.cao")
    V, F = load_triangles(cao)
    Vf, Ff = load_triangles(cao, primitives=False)
    assert len(Ff) == 12 and len(F) == 12 + 4 * CYLINDER_SEGMENTS
    assert V[F.ravel(), 2].max() == pytest.approx(BOX_M + H_M) and Vf[Ff.ravel(), 2].max() == pytest.approx(BOX_M)
    rng = np.random.default_rng(3)
    ang = rng.uniform(0, 2 * np.pi, 2000)
    z = rng.uniform(BOX_M + 0.01, BOX_M + H_M - 0.01, 2000)
    P = np.column_stack([BOX_M / 2 + R_M * np.cos(ang), BOX_M / 2 + R_M * np.sin(ang), z])
    cloud = tmp_path / "on_cylinder.xyz"
    np.savetxt(cloud, P)
    js = json.loads(mst("c2m", cloud, cao, "--json", "-q").stdout)
    sagitta = R_M * (1.0 - np.cos(np.pi / CYLINDER_SEGMENTS))
    assert js["mesh_triangles"] == len(F)
    assert js["unsigned"]["max"] <= sagitta * (1 + 1e-6)


def test_cylinder_with_a_zero_length_axis_is_bad_input(tmp_path, mst):
    p = tmp_path / "bad.cao"
    p.write_text("V1\n2\n0 0 0\n0 0 0\n0\n0\n0\n1\n0 1 0.05\n0\n")
    with pytest.raises(InputError, match="zero-length axis"):
        load_model(p)
    cloud = tmp_path / "c.xyz"
    np.savetxt(cloud, np.zeros((3, 3)))
    r = mst("c2m", cloud, p, check=False)
    assert r.returncode == 1 and "bad.cao" in r.stderr and "zero-length axis" in r.stderr


def test_a_circle_is_a_cylinder_rim_only_on_its_end(tmp_path):
    m = load_model(_box_and_cylinder(tmp_path / "cc.cao"))
    assert circle_on_cylinder_end(m, m.circles[0])
    V = m.vertices
    n = len(V)
    m.vertices = np.concatenate([V, [V[-4] + [0, 0, 0.05]]])  # a centre 5 cm down the axis
    assert not circle_on_cylinder_end(m, {**m.circles[0], "center": n})  # not at an end
    assert not circle_on_cylinder_end(m, {**m.circles[0], "radius": 2 * R_M})  # another radius


# ---------------------------------------------------------------------------- tracking (synthetic orbits)
def _orbit(tmp_path_factory, name, box):
    from mst.pipeline.synth import SynthConfig, synthesize

    d = tmp_path_factory.mktemp(name)
    cao = _box_and_cylinder(d / f"{name}.cao", box)
    s = synthesize("orbit", cao, d / "seq", SynthConfig(frames=12, width=640, height=480, depth=False,
                                                         aa_samples=4, texture_size=256))
    return d, cao, float(s["distance_m"])


@pytest.fixture(scope="module")
def box_cylinder(tmp_path_factory):
    return _orbit(tmp_path_factory, "cc", True)


def _track(mst, d, model, *extra):
    from mst.core.trajectory import read_tum

    seq = d / "seq"
    out = d / f"{model.stem}{'_'.join(extra).replace('-', '')}.txt"
    r = mst("track", seq / "rgb", "--model", model, "--camera", seq / "camera.json", "--init", seq / "cMo" / "000000.txt",
            "-o", out, "--fps", "30", "--slam", "off", "--json", *extra)
    return r, json.loads(r.stdout), read_tum(out)[1], read_tum(seq / "gt.txt")[1]


def test_box_and_cylinder_tracked_with_its_cylinder(box_cylinder, mst):
    """The ``.cao`` with a cylinder is tracked by render-based edges of the whole model (a note says so), every
    frame, at least as accurately as its box alone with polygon edges (whose run warns that the cylinder and the
    circle are not tracked), within issue #13's 10 % margin of a mesh against its polygon version."""
    from mst.core.poses import pose_error

    d, cao, dist = box_cylinder
    r, js, est, gt = _track(mst, d, cao)
    assert js["edges"] == "render" and js["tracked"] == js["frames"] == 12
    assert "1 cylinder(s) tracked" in r.stderr
    dt, dr = pose_error(est, gt)
    rp, jp, est_p, _ = _track(mst, d, cao, "--edges", "polygon")
    assert jp["edges"] == "polygon" and "1 cylinder(s), 1 circle(s) not tracked with polygon edges" in rp.stderr
    dt_p, dr_p = pose_error(est_p, gt[: len(est_p)])
    assert dt.mean() <= 1.1 * dt_p.mean() and dr.mean() <= 1.1 * dr_p.mean(), (dt.mean() / dist, dt_p.mean() / dist)


def test_cylinder_only_model_is_tracked(tmp_path_factory, mst):
    """A can (one cylinder and its top rim, no face) could not be tracked before ("model has no faces"): every frame
    is tracked, within issue #13's 0.3 % of the distance and 0.3 deg (modulo the turn about its axis, which its
    image does not show)."""
    from test_track_render import _error_modulo_z_symmetry

    d, cao, dist = _orbit(tmp_path_factory, "can", False)
    _, js, est, gt = _track(mst, d, cao)
    assert js["edges"] == "render" and js["tracked"] == js["frames"] == 12
    dt, dr = _error_modulo_z_symmetry(est, gt)
    assert dt.mean() <= 0.003 * dist and dr.mean() <= 0.3, (dt.mean() / dist, dr.mean())


def test_init_overlay_draws_the_cylinders_contour(tmp_path_factory, mst):
    """``mst init --overlay`` of a cylinder model draws the contour of its render at the pose (its limbs and rims),
    where a polygon model's edges would be drawn: the contour points lie on the image's edges (Canny, median
    distance <= 1 px), and a box without a cylinder gets no render contour (its polygon edges are drawn)."""
    import cv2

    from mst.core.camera import read_camera
    from mst.core.trajectory import read_pose_file
    from mst.pipeline.tracking.render_edges import contour_uv

    d, cao, _ = _orbit(tmp_path_factory, "can_overlay", False)
    seq = d / "seq"
    ov = d / "overlay.png"
    mst("init", "--model", cao, "--camera", seq / "camera.json", "--clicks", seq / "clicks.txt", "-o", d / "p0.txt",
        "--image", seq / "rgb" / "000000.png", "--overlay", ov, "-q")
    img = cv2.imread(str(seq / "rgb" / "000000.png"))
    pic = cv2.imread(str(ov))
    drawn = (pic[..., 1] == 255) & (pic[..., 0] < 100) & (pic[..., 2] < 100)  # pure green: the contour's dots
    assert drawn.sum() > 200
    uv = contour_uv(load_model(cao), cao, read_pose_file(d / "p0.txt"), read_camera(seq / "camera.json"))
    edges = cv2.Canny(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY), 50, 150)
    dist = cv2.distanceTransform((edges == 0).astype(np.uint8), cv2.DIST_L2, 3)
    ij = np.rint(uv).astype(int)
    assert len(uv) > 200 and np.median(dist[ij[:, 1], ij[:, 0]]) <= 1.0
    from mst.meshtools.generate import box_model

    box = tmp_path_factory.mktemp("box") / "box.cao"
    save_model(box, box_model((R_M, R_M, H_M)))
    assert contour_uv(load_model(box), box, read_pose_file(d / "p0.txt"), read_camera(seq / "camera.json")) is None


def test_circles_alone_are_named_in_the_error(tmp_path, mst):
    """A .cao of circles only cannot be tracked: `mst init` says so in one line naming the file, exit 1."""
    p = tmp_path / "rings.cao"
    p.write_text("V1\n3\n0 0 0\n0 0 1\n1 0 0\n0\n0\n0\n0\n1\n0.05 0 1 2\n")
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"model": "pinhole", "width": 640, "height": 480, "fx": 500.0, "fy": 500.0, "cx": 319.5,
                               "cy": 239.5, "dist": []}))
    r = mst("init", "--model", p, "--camera", cam, "--from-pose", "0", "-2", "0.5", "90", "0", "0", "-o",
            tmp_path / "p.txt", check=False)
    assert r.returncode == 1 and "rings.cao: model has no faces" in r.stderr and "1 circle(s)" in r.stderr
    assert not (tmp_path / "p.txt").exists()
