"""The inverse-depth buffer (numba scanline fill) against a per-pixel ray cast of the same faces."""

from __future__ import annotations

import numpy as np
import pytest


def _reference(geom, T, Ks, W, H, faces, near):
    """1/z at every buffer pixel centre: each face's plane hit by the pixel's ray, kept when the hit
    lies inside the face's outer loop and outside its holes (even-odd, in the image)."""
    from matplotlib.path import Path

    R, t = T[:3, :3], T[:3, 3]
    uu, vv = np.meshgrid(np.arange(W, dtype=float), np.arange(H, dtype=float))
    pts = np.column_stack([uu.ravel(), vv.ravel()])
    rays = np.column_stack([pts, np.ones(len(pts))]) @ np.linalg.inv(Ks).T  # camera z = 1
    best = np.zeros(len(pts))
    ids = np.full(len(pts), -1)
    for f in np.flatnonzero(faces):
        loops = [geom.faces[f], *geom.holes[f]]
        Xc = [geom.vertices[lp] @ R.T + t for lp in loops]
        if min(x[:, 2].min() for x in Xc) < near:
            continue  # the test poses keep every face in front of the near plane
        inside = np.zeros(len(pts), bool)
        for x in Xc:
            uv = x @ Ks.T
            inside ^= Path(uv[:, :2] / uv[:, 2:3]).contains_points(pts)
        n_c, p_c = R @ geom.face_normals[f], R @ geom.face_point[f] + t
        iz = (rays @ n_c) / (n_c @ p_c)
        win = inside & (iz > best)
        best = np.where(win, iz, best)
        ids = np.where(win, f, ids)
    return best.reshape(H, W), ids.reshape(H, W)


@pytest.fixture(scope="module")
def courtyard(tmp_path_factory):
    import subprocess
    import sys

    wrl = tmp_path_factory.mktemp("court") / "court.wrl"
    subprocess.run([sys.executable, "-m", "mst.meshtools.generate", "courtyard", "--polygons", "-o", str(wrl)], check=True)
    return wrl


@pytest.mark.parametrize("azimuth_deg", [20.0, 110.0, 200.0, 290.0])
def test_inverse_depth_buffer_matches_ray_cast(courtyard, azimuth_deg):
    """A courtyard building (a face with a hole, non-convex) from four sides. The buffer's coverage
    is conservative (pixel centres within half a pixel of a face, like cv2.fillPoly's), so: no
    pixel is farther than the ray cast (a nearer surface is never lost), and it differs from the ray
    cast only on pixels next to an outline of the ray-cast image (3x3 neighbourhood), exact to
    float32 rounding elsewhere."""
    from mst.core.poses import inv_T, look_at
    from mst.meshtools.formats import load_model
    from mst.pipeline.tracking.visibility import ModelGeometry, face_visibility, inverse_depth_buffer

    geom = ModelGeometry.from_model(load_model(courtyard))
    c = geom.vertices.mean(axis=0)
    a = np.radians(azimuth_deg)
    T = inv_T(look_at(c + np.array([30 * np.cos(a), 30 * np.sin(a), 18.0]), c))
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1.0]])
    fv = face_visibility(geom, T, None, 89.0, 89.0)
    buf, sc = inverse_depth_buffer(geom, T, K, 320, 240, fv, 0.1, 0.5)
    Ks = K.copy()
    Ks[:2] *= sc
    Ks[:2, 2] = (K[:2, 2] + 0.5) * sc - 0.5
    ref, ids = _reference(geom, T, Ks, buf.shape[1], buf.shape[0], fv, 0.1)
    import cv2

    assert (ref > 0).sum() > 500
    assert (buf >= ref * (1 - 1e-5)).all()  # conservative: never farther, never missing
    # outline pixels of the ray-cast image: a 3x3 neighbour shows another face (or none)
    k = np.ones((3, 3), np.uint8)
    id32 = ids.astype(np.float32)
    outline = cv2.dilate(id32, k) != cv2.erode(id32, k)
    differ = ~np.isclose(buf, ref, rtol=1e-5, atol=0)
    assert not (differ & ~outline).any(), int((differ & ~outline).sum())


@pytest.mark.parametrize("azimuth_deg", [0.0, 135.0])
def test_frustum_cull_changes_no_sample(courtyard, azimuth_deg):
    """A 5x5 block of courtyard buildings seen from inside the block, half of it behind the camera:
    the samples with the view-frustum cull are exactly those without it (it only skips work)."""
    import dataclasses

    from mst.core.poses import inv_T, look_at
    from mst.meshtools.formats import load_model
    from mst.meshtools.model import PolygonModel
    from mst.pipeline.tracking.visibility import ModelGeometry, visible_samples

    m = load_model(courtyard)
    V = np.asarray(m.vertices)
    Vs, Fs, Hs = [], [], []
    for i in range(5):
        for j in range(5):
            off = len(V) * len(Vs)
            Vs.append(V + [30.0 * i, 30.0 * j, 0.0])
            Fs += [np.asarray(f) + off for f in m.faces]
            Hs += [[np.asarray(h) + off for h in hh] for hh in (m.holes or [[] for _ in m.faces])]
    geom = ModelGeometry.from_model(PolygonModel(np.concatenate(Vs), Fs, Hs))
    plain = dataclasses.replace(geom, face_center=None, face_radius=None)
    a = np.radians(azimuth_deg)
    eye = np.array([70.0, 70.0, 25.0])
    T = inv_T(look_at(eye, eye + [40 * np.cos(a), 40 * np.sin(a), -20.0]))
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1.0]])
    args = (T, K, 320, 240, 4.0, 0.05, None, 80.0, 85.0)
    kw = dict(lod_min_line_px=12.0, lod_min_face_px2=64.0)
    S1, S0 = visible_samples(geom, *args, **kw), visible_samples(plain, *args, **kw)
    assert len(S0) > 100 and S0.stats["behind"] > 0
    np.testing.assert_array_equal(S1.uv, S0.uv)
    np.testing.assert_array_equal(S1.X_model, S0.X_model)


def test_reused_buffer_is_the_rendered_one(courtyard):
    """The per-model buffer cache (issue #14) returns a buffer only for the very inputs it was
    rendered for: the same bits as a fresh (uncached) rendering, read-only; a pose moved by 1e-12 m,
    another face set, scale or near plane renders anew; the erosion is reused with its buffer."""
    import cv2

    from mst.core.poses import inv_T, look_at
    from mst.meshtools.formats import load_model
    from mst.pipeline.tracking.depth_buffer import _render_buffer, eroded_buffer
    from mst.pipeline.tracking.visibility import ModelGeometry, face_visibility, inverse_depth_buffer

    geom = ModelGeometry.from_model(load_model(courtyard))
    c = geom.vertices.mean(axis=0)
    T = inv_T(look_at(c + np.array([30.0, 12.0, 18.0]), c))
    K = np.array([[262.5, 0, 159.5], [0, 262.5, 119.5], [0, 0, 1.0]])
    fv = face_visibility(geom, T, None, 89.0, 89.0)
    a, _ = inverse_depth_buffer(geom, T, K, 320, 240, fv, 0.1, 0.5)
    b, _ = inverse_depth_buffer(geom, T, K, 320, 240, fv.copy(), 0.1, 0.5)
    assert b is a and not a.flags.writeable
    assert np.array_equal(a, _render_buffer(geom, T, K, 320, 240, fv, 0.1, 0.5, None, False))
    T2 = T.copy()
    T2[0, 3] += 1e-12
    fv2 = fv.copy()
    fv2[np.flatnonzero(fv)[0]] = False
    for args in ((T2, fv, 0.1, 0.5), (T, fv2, 0.1, 0.5), (T, fv, 0.1, 0.25), (T, fv, 0.2, 0.5)):
        Ti, fi, near, sc = args
        d, _ = inverse_depth_buffer(geom, Ti, K, 320, 240, fi, near, sc)
        assert d is not a
        assert np.array_equal(d, _render_buffer(geom, Ti, K, 320, 240, fi, near, sc, None, False))
    buf, nb, _ = eroded_buffer(geom, T, K, 320, 240, fv, 0.1, 0.5)
    assert np.array_equal(nb, cv2.erode(buf, np.ones((3, 3), np.uint8)))
    assert eroded_buffer(geom, T, K, 320, 240, fv, 0.1, 0.5)[1] is nb
