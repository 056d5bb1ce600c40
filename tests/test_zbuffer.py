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
        best = np.where(inside & (iz > best), iz, best)
    return best.reshape(H, W)


@pytest.fixture(scope="module")
def courtyard(tmp_path_factory):
    import subprocess
    import sys

    wrl = tmp_path_factory.mktemp("court") / "court.wrl"
    subprocess.run([sys.executable, "-m", "mst.meshtools.generate", "courtyard", "--polygons", "-o", str(wrl)], check=True)
    return wrl


@pytest.mark.parametrize("azimuth_deg", [20.0, 110.0, 200.0, 290.0])
def test_inverse_depth_buffer_matches_ray_cast(courtyard, azimuth_deg):
    """A courtyard building (a face with a hole, non-convex) from four sides: both use the
    pixel-centre rule, so they agree to float32 rounding except where a pixel centre lies on a face
    outline to rounding (0 of ~4500 covered pixels measured): at most 1 %."""
    from mst.meshtools.io import load_model
    from mst.pipeline.poses import inv_T, look_at
    from mst.pipeline.visibility import ModelGeometry, face_visibility, inverse_depth_buffer

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
    ref = _reference(geom, T, Ks, buf.shape[1], buf.shape[0], fv, 0.1)
    covered = (ref > 0) | (buf > 0)
    assert covered.sum() > 500
    differ = ~np.isclose(buf, ref, rtol=1e-5, atol=0)
    assert differ.sum() <= 0.01 * covered.sum(), (differ.sum(), covered.sum())
