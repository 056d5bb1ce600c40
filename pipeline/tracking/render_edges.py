"""Render-based edges ("dynamic edgelets") for :class:`mst.pipeline.tracking.EdgeTracker`: any triangle mesh is a model.

:class:`RenderEdgeProvider` replaces the polygon-edge samples of the tracker
(``EdgeTracker.sample_provider``): for a pose it returns a :class:`mst.pipeline.tracking.visibility.Samples`
built from the edgelets of a render (:func:`mst.pipeline.tracking.edgelets.extract_edgelets`): each edgelet is
its own short model "edge" ``X +- h t`` (h = 2 % of its depth), so the moving-edge search along the
2D normal and the robust VVS (point-to-line distance, Tukey IRLS) run unchanged; hidden-line
removal, near-plane clipping and face visibility come from the render.

**Re-render rule.** The edgelet set of the last render is kept and reprojected while the camera
stays close to the render viewpoint. A crease is fixed on the mesh, but the occluding contour of a
smooth surface (its silhouette) is the set of points where the view ray grazes the surface, and it
depends only on the *camera centre* in the model frame (a rotation about the centre does not move
it). When the view direction turns by ``a`` (radians) the old contour points of a surface of
curvature radius ``rho`` project ``rho (1 - cos a) ~ rho a^2 / 2`` inside the true contour, i.e.
``f rho a^2 / (2 D)`` pixels at distance ``D``. The provider re-renders when the camera centre has
moved by more than ``a_max D`` with ``a_max = sqrt(2 bias_px D / (f rho))`` (``bias_px`` = 0.1 px,
``rho`` = the mesh's bounding radius, an upper bound of the curvature radius of its curved parts;
clamped to [0.2, 3] deg), or when the camera has turned by more than ``max_turn_deg`` (new parts of
the contour entering the image). The tracker runs two edge passes per frame in this mode, so the
second pass re-renders at the first pass's pose whenever the frame's motion exceeds the rule: the
silhouette used for the final pose is at most ``a_max`` old, a bias below ``bias_px``. (A polyhedral
mesh's contours lie on mesh edges and do not slide; the same rule is kept for it: on the box TIN
orbit, re-rendering only after 5 deg gave 7 % larger errors than this rule, 2 passes than 1: the
fresh render's points at the current pose are the better sample.)

**Contour measurements.** On a curved mesh the moving-edge search runs with a 3-px mask
(``RENDER_MASK_PX``) instead of the configured ``mask_px``: on a smooth object the shading darkens steeply
toward the rim, and a wider mask mixes that ramp into the step (blob / vase orbit at the true pose, 640x480: spread of the silhouette
offsets within 1 px 0.36 -> 0.28 px, pose error from the true pose 0.36 -> 0.29 % and 0.56 -> 0.37 % of the
distance). A silhouette or self-occlusion candidate must also keep the object on its inner side
(:func:`contour_side_test`): a background texture edge next to the silhouette has background there
(silhouette candidates > 1 px off at the true pose: 21 -> 10 %). A parabolic peak on a 1/4-px bilinear
gradient profile (smoothed or not) was measured and not kept: it spread the offsets more (0.28 -> 0.31 px).
On a curved mesh every kept silhouette candidate is then moved onto the image's sub-pixel contour
(:func:`crossing_offsets`: the crossing with the middle of the step between the object's level, extrapolated along
its shading ramp, and the background's): the mask's peak is pulled toward the ramp's bright side by 0.1-0.2 px,
with the sign of the contrast, which the pose absorbs as a shift (vase orbit / fast 0.34 / 0.35 -> 0.27 / 0.22 % of
the distance, blob fast 1.1 -> 0.60 %). A polyhedral mesh (a TIN of a box, a building) has no rim ramp and keeps ``mask_px`` and the plain peak (the
crossing raised the box TIN orbit's errors from 1.07x to 1.37x the polygon model's): on the real tea box TIN
the 3-px mask with the side test moved the poses 5.1 mm from the polygon model's (max), the 5-px one 2.1 mm.

**Bodies of revolution.** A torus, a vase, a bottle (:func:`revolution_axis`) look the same from every camera
turned about their axis: that twist is a gauge of the pose, not an uncertainty, so :meth:`RenderEdgeProvider.gauge_cov`
fixes it in the covariance the error budget reads and :meth:`RenderEdgeProvider.align_to` compares two poses
modulo it (the budget's ambiguity and first-frame tests).

:func:`choose_edges` implements ``mst track --edges auto``: polygon edges for polygon formats
(``.cao``, ``.wrl``) and small planar triangle files (today's behaviour), render-based edges for
triangle meshes with many faces (> ``MANY_FACES``) or curved parts.

Longer than 500 lines: the render-edge provider, its re-render rule and its extra passes act on one cached render state; split they would pass it around.
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np

from mst import InputError
from mst.core.poses import matmul_exact
from mst.errors import ConfigError
from mst.pipeline.tracking.compiled import kernels as _kc  # ahead of time or numba JIT
from mst.pipeline.tracking.exact import centre, dot3, eigh, mv, norm3, rigid

log = logging.getLogger(__name__)

#: a triangle-only model with more faces than this is tracked with render-based edges under --edges auto
MANY_FACES = 1000
#: a mesh whose non-flat edges are smooth (dihedral < the crease angle) in more than this share is curved
CURVED_SHARE = 0.05
#: render resolution (fraction of the image). 1/4 makes renders 4x cheaper and kept the torus orbit at
#: 640x480 as accurate (0.172 % / 0.109 deg against 0.157 % / 0.105 deg modulo its symmetry), but the real
#: tea box TIN drifted farther from the polygon poses (max 3.3 mm / 0.45 deg against 2.6 mm / 0.37 deg)
RENDER_SCALE = 0.5
#: polygon formats: --edges auto keeps their polygon edges
#: moving-edge mask size of render-based edges, px (see the module doc)
RENDER_MASK_PX = 3
POLYGON_SUFFIXES = (".cao", ".wrl", ".vrml")
#: a curved mesh's frame gets up to this many edge passes beyond the configured ones while the last pass still
#: moved its contour by more than ``bias_px`` (0.1 px) along the normals at the median sample: a start far from
#: the frame's pose (fast motion, an aid's prediction 3.7 deg off). Measured at 640x480, 16 frames: converged
#: second passes move it <= 0.06 px (torus / blob / vase orbit: no extra pass, unchanged), unconverged ones
#: 0.1-3.3 px; vase fast with the aid 15 -> 16 of 16 frames (0.223 % / 0.159 deg mean), the others unchanged
EXTRA_PASSES = 2
#: --edges auto merges a closed polyhedral triangle mesh into planar polygons when they number at most this
#: share of its triangles (a box TIN: 6 of 4,800; a scan whose "planes" are not planar stays render-based)
MERGE_MAX_SHARE = 0.1


def mesh_triangles(model, path=None) -> tuple[np.ndarray, np.ndarray]:
    """(V (N,3) m, F (M,3) int64) of a model, degenerate (zero-area) triangles removed.

    Raises :class:`mst.InputError` when no triangle with an area is left.
    """
    from mst.meshtools.solids import model_triangles

    V, F = model_triangles(model)  # with a .cao's cylinders as closed surfaces
    if len(F):
        e1 = V[F[:, 1]] - V[F[:, 0]]
        e2 = V[F[:, 2]] - V[F[:, 0]]
        area2 = np.linalg.norm(np.cross(e1, e2), axis=1)
        scale = max(float(np.ptp(V, axis=0).max()), 1e-300)
        F = F[area2 > 1e-12 * scale * scale]
    if not len(F):
        raise InputError(path, "model has no triangle with a non-zero area (degenerate faces only)")
    return V, F


def curved_fraction(V: np.ndarray, F: np.ndarray, flat_deg: float = 1.0, crease_deg: float = 40.0) -> float:
    """Share of the non-flat interior edges of the mesh whose dihedral angle is below ``crease_deg``.

    A polyhedron (box, building) has only flat (coplanar triangulation diagonals) and sharp edges: 0;
    a tessellated smooth surface has mostly small, non-zero dihedral angles: near 1.
    """
    if len(F) < 2:
        return 0.0
    e1 = V[F[:, 1]] - V[F[:, 0]]
    e2 = V[F[:, 2]] - V[F[:, 0]]
    n = np.cross(e1, e2)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    fid = np.tile(np.arange(len(F)), 3)
    key = E[:, 0] * (int(E.max()) + 1) + E[:, 1]
    order = np.argsort(key, kind="stable")
    ks = key[order]
    pair = np.nonzero(ks[1:] == ks[:-1])[0]
    if not len(pair):
        return 0.0
    f0, f1 = fid[order[pair]], fid[order[pair + 1]]
    ang = np.degrees(np.arccos(np.clip(np.abs((n[f0] * n[f1]).sum(1)), -1.0, 1.0)))
    bent = ang > flat_deg
    if not bent.any():
        return 0.0
    return float((ang[bent] < crease_deg).mean())


def choose_edges(model, model_path, mode: str) -> str:
    """``'polygon'`` or ``'render'`` for the edge source ``mode`` (auto|polygon|render); see the module doc."""
    if mode in ("polygon", "render"):
        return mode
    if mode != "auto":
        raise ConfigError("edge_source", f"must be one of auto, polygon, render, got {mode!r}")
    if getattr(model, "cylinders", None):  # a .cao's cylinders: their limbs are the render's silhouettes
        return "render"
    if Path(model_path).suffix.lower() in POLYGON_SUFFIXES:
        return "polygon"
    faces = model.faces
    if not len(faces) or any(len(f) != 3 for f in faces):
        return "polygon"
    if len(faces) > MANY_FACES:
        return "render"
    V, F = model.triangulate()
    return "render" if curved_fraction(np.asarray(V, float), np.asarray(F, np.int64)) > CURVED_SHARE else "polygon"


def _is_closed(F: np.ndarray) -> bool:
    """Every edge of the triangles ``F`` is shared by exactly two of them (a closed, edge-manifold surface)."""
    E = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    key = E[:, 0] * (int(E.max()) + 1) + E[:, 1]
    _, counts = np.unique(key, return_counts=True)
    return bool((counts == 2).all())


def merge_polyhedral_tin(model, model_path, mode: str):
    """``--edges auto`` on a closed polyhedral triangle mesh with many faces (a box or building TIN): its coplanar,
    edge-connected triangles merged into planar polygons (:func:`mst.meshtools.convert.tin_to_polygons`, what
    ``mst convert-model`` does), or ``None`` (keep the model as it is).

    The merged model is tracked with polygon edges: the same edges, the same samples along them (spacing, level of
    detail, face visibility) as the polygon version of the object, where render-based edgelets of the TIN are a
    different sample of the same contours (the real tea box: 2.1 mm / 0.37 deg from the polygon poses). Only
    closed meshes are merged (an open patch has no outward side for the polygon path's face culling); a curved
    mesh, or one whose planes do not merge (more than ``MERGE_MAX_SHARE`` polygons per triangle), stays
    render-based.
    """
    if mode != "auto" or Path(model_path).suffix.lower() in POLYGON_SUFFIXES:
        return None
    faces = model.faces
    if len(faces) <= MANY_FACES or any(len(f) != 3 for f in faces) or any(len(h) for h in model.holes):
        return None
    V, F = mesh_triangles(model, model_path)
    if curved_fraction(V, F) > CURVED_SHARE or not _is_closed(F):
        return None
    from mst.meshtools.convert import tin_to_polygons

    try:
        poly, res = tin_to_polygons(V, F, path=str(model_path))
    except InputError:
        return None
    if poly.n_faces > MERGE_MAX_SHARE * len(F):
        return None
    log.info(f"polyhedral mesh: {len(F)} triangles merged into {poly.n_faces} planar polygons, tracked with their "
             "polygon edges")
    return poly


#: a mesh is a body of revolution about a principal axis of its surface when its vertices turned about that axis
#: by these angles lie within SYMMETRY_TOL x its diagonal of its surface (a tessellated one: within its facets'
#: sagitta, 1e-4 of the size for the generated torus and vase)
SYMMETRY_TURNS_DEG = (7.0, 31.0, 97.0)
SYMMETRY_TOL = 2e-3


def revolution_axis(renderer, max_points: int = 2000):
    """``(axis (3,) unit, point (3,))`` in the model frame when the mesh of ``renderer`` is a body of revolution
    (torus, vase, bottle, cylinder), else None. Candidates: the principal axes of the surface (area-weighted
    triangle centroids) whose two other moments agree within 2 %; kept when the mesh turned about the axis by each
    of ``SYMMETRY_TURNS_DEG`` maps onto itself (vertex distance to the surface, Embree)."""
    import open3d as o3d

    V, F = renderer.V, renderer.F
    A = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    if A.sum() <= 0:
        return None
    C = V[F].mean(1)
    mu = (A[:, None] * C).sum(0) / A.sum()
    D = C - mu
    lam, vec = eigh((A[:, None, None] * D[:, :, None] * D[:, None, :]).sum(0) / A.sum())
    diag = norm3(np.ptp(V, axis=0))
    P = V[np.unique(np.linspace(0, len(V) - 1, min(max_points, len(V))).astype(np.int64))]
    for k in range(3):
        o = np.delete(lam, k)
        if abs(o[0] - o[1]) > 0.02 * max(abs(o).max(), 1e-300):
            continue
        a = vec[:, k]
        ok = True
        for deg in SYMMETRY_TURNS_DEG:
            th = np.radians(deg)
            Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
            Rm = np.eye(3) + np.sin(th) * Kx + (1 - np.cos(th)) * matmul_exact(Kx, Kx)
            Q = rigid(P - mu, Rm) + mu - renderer.origin
            d = renderer.scene.compute_distance(o3d.core.Tensor(Q.astype(np.float32))).numpy()
            if float(d.max()) > SYMMETRY_TOL * diag:
                ok = False
                break
        if ok:
            return a, mu
    return None


class RenderEdgeProvider:
    """Edge samples from renders of a triangle mesh (see the module doc).

    ``V`` (N,3) m, ``F`` (M,3) model frame; ``camera`` the full-resolution camera (K, width, height).
    ``samples(T_cam_model, K, W, H)`` -> :class:`mst.pipeline.tracking.visibility.Samples` for the image of
    intrinsics ``K`` (the tracker's pyramid levels pass scaled ones); statistics: ``n_renders``,
    ``render_ms`` (total extraction time, wall), ``render_cpu_ms`` (its process CPU time).
    """

    def __init__(self, V: np.ndarray, F: np.ndarray, camera, *, scale: float = RENDER_SCALE, budget: int = 300,
                 crease_deg: float = 40.0, bias_px: float = 0.1, max_turn_deg: float = 5.0, border_px: int = 3,
                 near_m: float = 0.1):
        from mst.pipeline.render import Renderer

        self.renderer = Renderer(V, F)
        n = self.renderer.normals
        self.renderer.normals = np.where(np.isfinite(n), n, 0.0)
        self.cam = camera
        self.K = np.asarray(camera.K, np.float64)
        self.W, self.H = int(camera.width), int(camera.height)
        self.scale, self.budget, self.crease_deg = scale, budget, crease_deg
        self.bias_px, self.max_turn_deg, self.border_px, self.near_m = bias_px, max_turn_deg, border_px, near_m
        lo, hi = V.min(0), V.max(0)
        self.centre_model = 0.5 * (lo + hi)
        self.radius_m = 0.5 * norm3(hi - lo)
        self.cache = None  # Edgelets of the last render
        self.curved = False  # a curved mesh: its rims' measurements move onto the ramp crossing (filter_matches)
        self.axis = revolution_axis(self.renderer)  # (axis, point) model frame of a body of revolution, or None
        self.extra_passes = 0  # edge passes the tracker may add while unconverged() (curved meshes: EXTRA_PASSES)
        self.n_renders = 0
        self.render_ms = 0.0  # wall
        self.render_cpu_ms = 0.0  # process CPU time (every thread of the ray caster)

    def gauge_cov(self, T_cam_model: np.ndarray, W: np.ndarray, cov: np.ndarray, rms_px: float,
                  jk: tuple | None = None) -> np.ndarray:
        """The pose covariance ``cov`` (6x6, twist ``(v, w)`` of ``T_cam_model``) with the mesh's symmetry fixed:
        for a body of revolution (:func:`revolution_axis`) a turn of the model about its axis changes no image, so
        its twist is a gauge freedom (any value is as right as any other) and not an uncertainty of the pose: the
        covariance is ``rms^2 (W + lambda n n^T)^-1`` for the unit twist ``n`` of that turn (lambda: 1e6 x the
        largest diagonal of the information ``W``); with the solve's cluster-covariance inputs ``jk``
        (:attr:`VVSResult.jk_inputs`) the cluster-robust covariance with the same ``lambda n n^T``
        (:func:`mst.pipeline.tracking.covariance.edge_cluster_cov`). Other meshes: ``cov`` unchanged."""
        if self.axis is None or W is None or cov is None or not np.isfinite(W).all():
            return cov
        a, p = self.axis
        R, t = T_cam_model[:3, :3], T_cam_model[:3, 3]
        w = mv(R, a)
        n = np.concatenate([np.cross(mv(R, p) + t, w), w])  # rotation about the axis through R p + t (camera frame)
        n /= math.sqrt(float(np.sum(n * n)))
        lam = 1e6 * float(np.abs(np.diag(W)).max())
        try:
            from mst.pipeline.tracking.exact import inverse

            C_fixed = float(rms_px) ** 2 * inverse(W + lam * np.outer(n, n))
        except np.linalg.LinAlgError:
            return cov
        if jk is not None:
            from mst.pipeline.tracking.covariance import edge_cluster_cov, psd_max

            C = edge_cluster_cov(*jk, gauge=n, gauge_lambda=lam)[0]
            if C is not None:
                return psd_max(C_fixed, C)
        return C_fixed

    def align_to(self, T_ref: np.ndarray, T: np.ndarray) -> np.ndarray:
        """``T`` (T_cam_model) with the model turned about its axis of revolution so that the camera centre's angle
        about the axis is ``T_ref``'s: two poses of a body of revolution compared modulo its symmetry; ``T`` itself
        for other meshes."""
        if self.axis is None:
            return T
        a, p = self.axis
        c, cr = centre(T) - p, centre(T_ref) - p
        c, cr = c - dot3(c, a) * a, cr - dot3(cr, a) * a  # in the plane normal to the axis
        if norm3(c) < 1e-12 or norm3(cr) < 1e-12:
            return T
        th = math.atan2(dot3(np.cross(cr, c), a), dot3(cr, c))  # turn of the model taking c's angle to cr's
        Kx = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
        Rm = np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * matmul_exact(Kx, Kx)
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = Rm, p - mv(Rm, p)
        return matmul_exact(T, M)

    def unconverged(self, S, T_from: np.ndarray, T_to: np.ndarray) -> bool:
        """The edge pass from ``T_from`` to ``T_to`` moved the samples ``S`` by more than ``bias_px`` along their
        normals at the median: its matches were searched around a pose that far from the frame's, search again.
        (Along the normals only: a body of revolution's turn about its axis slides its contour points unseen.)"""
        K = self.K

        def proj(T):
            Xc = rigid(S.X_model, T[:3, :3], T[:3, 3])
            z = np.maximum(Xc[:, 2], 1e-9)
            return np.stack([K[0, 0] * Xc[:, 0] / z, K[1, 1] * Xc[:, 1] / z], 1)

        if S is None or not len(S.X_model):
            return False
        return float(np.median(np.abs(((proj(T_to) - proj(T_from)) * S.normal).sum(1)))) > self.bias_px

    def stats(self) -> dict:
        """Render statistics for the run summary: renders, total and mean extraction time (ms)."""
        return {"renders": self.n_renders, "render_ms_total": round(self.render_ms, 3),
                "render_ms_mean": round(self.render_ms / self.n_renders, 3) if self.n_renders else None}

    # ------------------------------------------------------------------ re-render rule
    def max_view_turn_rad(self, T_cam_model: np.ndarray) -> float:
        """``a_max`` of the re-render rule at this pose (radians)."""
        c = centre(T_cam_model)
        D = max(norm3(c - self.centre_model), 1e-9)
        f = float(max(self.K[0, 0], self.K[1, 1]))
        a = math.sqrt(2.0 * self.bias_px * D / (f * max(self.radius_m, 1e-9)))
        return float(np.clip(a, math.radians(0.2), math.radians(3.0)))

    def stale(self, T_cam_model: np.ndarray) -> bool:
        """True when the cached edgelets are too old for this pose (the rule of the module doc)."""
        if self.cache is None:
            return True
        Tr = self.cache.T_cam_model
        c = centre(T_cam_model)
        cr = centre(Tr)
        D = max(norm3(cr - self.centre_model), 1e-9)
        if norm3(c - cr) > self.max_view_turn_rad(Tr) * D:
            return True
        dR = matmul_exact(T_cam_model[:3, :3], Tr[:3, :3].T)
        turn = math.degrees(math.acos(float(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0))))
        return turn > self.max_turn_deg

    def render(self, T_cam_model: np.ndarray):
        """Extract (and cache) the edgelets at this pose."""
        from mst.pipeline.tracking.edgelets import extract_edgelets

        t0, c0 = time.perf_counter(), time.process_time()
        self.cache = extract_edgelets(self.renderer, T_cam_model, self.K, self.W, self.H, scale=self.scale,
                                      crease_deg=self.crease_deg, budget=self.budget, border_px=self.border_px,
                                      near_m=self.near_m)
        self.render_ms += (time.perf_counter() - t0) * 1000.0
        self.render_cpu_ms += (time.process_time() - c0) * 1000.0
        self.n_renders += 1
        return self.cache

    # ------------------------------------------------------------------ the tracker's sample source
    def samples(self, T_cam_model: np.ndarray, K: np.ndarray, width: int, height: int):
        """Samples of the (cached or new) edgelets projected with ``K`` at ``T_cam_model`` (image W x H)."""
        from mst.pipeline.tracking.edgelets import project_lines
        from mst.pipeline.tracking.visibility import Samples

        T = np.asarray(T_cam_model, np.float64)
        if self.stale(T):
            self.render(T)
        e = self.cache
        Xc = rigid(e.X_model, T[:3, :3], T[:3, 3])
        z = Xc[:, 2]
        front = z > self.near_m
        h = 0.02 * np.where(front, z, 1.0)
        uv, nrm = project_lines(e.X_model, e.t_model, T, K, h)
        b = self.border_px
        keep = (front & np.isfinite(uv).all(1) & np.isfinite(nrm).all(1) & (uv[:, 0] >= b) & (uv[:, 0] <= width - 1 - b)
                & (uv[:, 1] >= b) & (uv[:, 1] <= height - 1 - b))
        self.kind = e.kind[keep]  # of the samples just returned (the side test of filter_matches)
        X = e.X_model[keep]
        t = e.t_model[keep]
        hk = h[keep][:, None]
        A, B = X - hk * t, X + hk * t
        uv, nrm = uv[keep], nrm[keep]
        d = np.stack([nrm[:, 1], -nrm[:, 0]], 1) * (0.02 * K[0, 0])
        edge_uv = np.stack([uv - d, uv + d], 1)
        return Samples(uv, nrm, X, np.arange(len(X)), A, B, edge_uv, np.zeros(0, bool))


    def explain(self, S) -> str:
        """Why the samples ``S`` of the last pose are too few (render-based edges)."""
        e = self.cache
        if e is None or (e.n_candidates == 0 and len(e) == 0):
            return ("no contour of the mesh in view at this pose (no silhouette, self-occlusion or crease: the "
                    "mesh is out of the image, or the view lies inside a smooth or flat surface)")
        return (f"too few contour points in view ({len(S)} edgelet samples from {e.n_candidates} contour pixels "
                "of the render)")

    def filter_matches(self, img: np.ndarray, K: np.ndarray, S, m, ref_img: np.ndarray, ref_T: np.ndarray):
        """Drop the moving-edge candidates of occluding-contour samples whose object side does not look like
        the object (see :func:`contour_side_test`); returns ``m`` with those offsets NaN, the best kept first."""
        from mst.pipeline.tracking.edgelets import CREASE

        occluding = self.kind != CREASE
        if not occluding.any():
            return m
        ok = contour_side_test(img, K, S.uv, S.normal, S.X_model, m.offset, m.normal, ref_img, ref_T)
        ok |= ~occluding[:, None]
        off = np.where(ok & np.isfinite(m.offset), m.offset, np.nan)
        if self.curved:  # a smooth rim's sub-pixel position: the crossing with its shading ramp (crossing_offsets)
            moved = np.where(occluding[:, None], crossing_offsets(img, S.uv, S.normal, off, m.normal), np.nan)
            off = np.where(np.isfinite(moved), moved, off)
        order = np.argsort(~np.isfinite(off), axis=1, kind="stable")  # kept candidates first, in rank order
        rows = np.arange(len(off))[:, None]
        m.offset, m.likelihood = off[rows, order], np.where(np.isfinite(off), m.likelihood, 0.0)[rows, order]
        return m


#: the object side of an occluding contour is read this far inside it (px): beyond the 5-px mask's reach
SIDE_PX = (2.0, 3.0)
#: a candidate's object side may differ from the reference by this share of the reference contrast
SIDE_TOL = 0.5
#: ... or by this many gray levels (image noise, shading change between frames)
SIDE_TOL_MIN = 6.0


def _gray_at(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    from mst.pipeline.tracking.edgelets import _bilinear

    return _bilinear(img, uv[..., 0].ravel(), uv[..., 1].ravel()).reshape(uv.shape[:-1])


#: object side of the crossing's profile: the shading ramp is fitted this far inside the candidate (px; beyond the
#: 1-px anti-aliased step and the 3-px mask); the background level is read at BG_PX outside
RAMP_PX = (1.5, 3.5)
BG_PX = (1.5, 3.0)
#: the crossing is searched within this distance of the moving-edge candidate (px), on a profile of PROFILE_STEP_PX
CROSS_PX = 1.5
PROFILE_STEP_PX = 0.25


def crossing_offsets(img, uv, n_out, offset, normal) -> np.ndarray:
    """(N, C) offsets of the candidates moved onto the sub-pixel position of the occluding contour, NaN where none.

    Along the outward normal ``n_out`` through each candidate the bilinear image profile ``p(t)`` is read every
    ``PROFILE_STEP_PX``; the object side is fitted with a line ``a + b t`` over ``RAMP_PX`` inside (the shading of
    a smooth surface darkens or brightens steadily toward its rim), the background level ``g`` is the mean over
    ``BG_PX`` outside. The contour is where ``p(t)`` crosses ``(a + b t + g) / 2``, the middle of the
    anti-aliased step between the object's extrapolated level and the background: the mask's correlation peak
    is pulled toward the ramp's bright side (measured at the true poses of the vase orbit, by edge normal sector:
    -0.16..-0.23 px where the object is brighter than the floor, +0.10..+0.19 px where it is darker; after:
    within +-0.1 px). Kept only with exactly one crossing within ``CROSS_PX`` and a step above ``SIDE_TOL_MIN``.

    One numba kernel (:func:`mst.pipeline.tracking.kernels.contour_crossings`: the operations of
    :func:`crossing_offsets_numpy` in their order, the same bits; issue #14: 1.9 ms a call on the box-and-cylinder
    orbit's ~250 contour samples x 2 candidates, two calls a frame).
    """
    contour_crossings = _kc.contour_crossings

    t, ramp, bg, win = _profile_layout()
    ti = t[ramp]
    tm = ti.mean()
    tc = ti - tm
    sgn = np.sign((n_out * normal).sum(1))
    out = np.empty(np.shape(offset))
    from mst.pipeline.tracking.moving_edges import _image

    # 8-bit gray levels are read as they are (exact in float64, as through the formulation's float32 copy)
    return contour_crossings(_image(img), np.ascontiguousarray(uv, np.float64),
                             np.ascontiguousarray(n_out, np.float64), np.ascontiguousarray(offset, np.float64),
                             np.ascontiguousarray(normal, np.float64), sgn, t, ramp, tc, float((tc ** 2).sum()),
                             float(tm), bg, win, float(PROFILE_STEP_PX), float(SIDE_TOL_MIN), out)


def _profile_layout():
    """``(t, ramp, bg, win)``: the abscissae of :func:`crossing_offsets`'s profile (px along the outward normal) and
    the indices of its object ramp (``RAMP_PX`` inside), its background (``BG_PX`` outside) and its crossing window
    (``CROSS_PX``)."""
    t = np.arange(-4.0, 4.0 + 1e-9, PROFILE_STEP_PX)
    ramp = np.flatnonzero((t >= -RAMP_PX[1] - 1e-9) & (t <= -RAMP_PX[0] + 1e-9))
    bg = np.flatnonzero((t >= BG_PX[0] - 1e-9) & (t <= BG_PX[1] + 1e-9))
    win = np.flatnonzero(np.abs(t) <= CROSS_PX + 1e-9)
    return t, ramp, bg, win


def crossing_offsets_numpy(img, uv, n_out, offset, normal) -> np.ndarray:
    """The numpy formulation of :func:`crossing_offsets` (the reference of its kernel's test)."""
    t = np.arange(-4.0, 4.0 + 1e-9, PROFILE_STEP_PX)
    sgn = np.sign((n_out * normal).sum(1))[:, None]  # offsets are along the search normal: +-n_out
    c = uv[:, None, :] + np.nan_to_num(offset)[..., None] * normal[:, None, :]  # (N, C, 2)
    prof = _gray_at(img.astype(np.float32), c[:, :, None, :] + t[None, None, :, None] * n_out[:, None, None, :])
    ins = (t >= -RAMP_PX[1] - 1e-9) & (t <= -RAMP_PX[0] + 1e-9)
    ti, pi = t[ins], prof[..., ins]
    tm = ti.mean()
    b = ((pi - pi.mean(-1, keepdims=True)) * (ti - tm)).sum(-1) / ((ti - tm) ** 2).sum()
    a = pi.mean(-1) - b * tm
    g = prof[..., (t >= BG_PX[0] - 1e-9) & (t <= BG_PX[1] + 1e-9)].mean(-1)
    win = np.abs(t) <= CROSS_PX + 1e-9
    tw = t[win]
    d = prof[..., win] - 0.5 * (a[..., None] + b[..., None] * tw + g[..., None])
    sg = np.sign(d)
    ch = sg[..., 1:] != sg[..., :-1]
    j = np.argmax(ch, axis=-1)
    p0 = np.take_along_axis(d, j[..., None], -1)[..., 0]
    p1 = np.take_along_axis(d, j[..., None] + 1, -1)[..., 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = tw[j] + PROFILE_STEP_PX * p0 / (p0 - p1)
    good = (ch.sum(-1) == 1) & np.isfinite(offset) & (np.abs(a - g) > SIDE_TOL_MIN)
    return np.where(good, offset + sgn * tc, np.nan)


def contour_side_test(img, K, uv, n_out, X_model, offset, normal, ref_img, ref_T) -> np.ndarray:
    """(N, C) bool: candidates of occluding-contour samples whose object side matches the reference frame.

    A silhouette separates the object from whatever lies behind it; a texture edge of the background next to
    it has background on both sides. In the reference frame (``ref_img`` at its pose ``ref_T``, the last good
    pose) each sample's gray level is read ``SIDE_PX`` inside the contour (``-n_out``, the object) and outside
    (the background); a candidate at ``uv + offset * normal`` is kept when the gray level ``SIDE_PX`` on its
    object side is within ``max(SIDE_TOL x |contrast|, SIDE_TOL_MIN)`` of the reference's object side: a
    background edge's inner side is background, ``|contrast|`` away. Blob orbit at the true pose (640x480):
    21 % of silhouette candidates > 1 px off before.
    """
    contour_sides = _kc.contour_sides

    Xc = rigid(X_model, ref_T[:3, :3], ref_T[:3, 3])
    z = np.maximum(Xc[:, 2], 1e-9)
    uvp = np.stack([K[0, 0] * Xc[:, 0] / z + K[0, 2], K[1, 1] * Xc[:, 1] / z + K[1, 2]], 1)
    # the reads and the test in one kernel (the operations of contour_side_test_numpy in their order, the same bits)
    ok = np.empty(np.shape(offset), np.bool_)
    return contour_sides(_kernel_image(img), _kernel_image(ref_img), np.ascontiguousarray(uv, np.float64), uvp,
                         np.ascontiguousarray(n_out, np.float64), np.ascontiguousarray(offset, np.float64),
                         np.ascontiguousarray(normal, np.float64), np.asarray(SIDE_PX, np.float64), float(SIDE_TOL),
                         float(SIDE_TOL_MIN), ok)


def _kernel_image(img: np.ndarray) -> np.ndarray:
    """The image as the contour kernels read it: C-contiguous uint8, float32 or float64 (others as float64)."""
    if img.dtype in (np.uint8, np.float32, np.float64):
        return np.ascontiguousarray(img)
    return np.ascontiguousarray(img, np.float64)


def contour_side_test_numpy(img, K, uv, n_out, X_model, offset, normal, ref_img, ref_T) -> np.ndarray:
    """The numpy formulation of :func:`contour_side_test` (the reference of its kernel's test)."""
    Xc = rigid(X_model, ref_T[:3, :3], ref_T[:3, 3])
    z = np.maximum(Xc[:, 2], 1e-9)
    uvp = np.stack([K[0, 0] * Xc[:, 0] / z + K[0, 2], K[1, 1] * Xc[:, 1] / z + K[1, 2]], 1)
    d = np.asarray(SIDE_PX)[:, None, None]
    ref_in = _gray_at(ref_img, uvp[None] - d * n_out[None]).mean(0)
    ref_out = _gray_at(ref_img, uvp[None] + d * n_out[None]).mean(0)
    tol = np.maximum(SIDE_TOL * np.abs(ref_in - ref_out), SIDE_TOL_MIN)
    c = uv[:, None, :] + np.nan_to_num(offset)[..., None] * normal[:, None, :]  # (N, C, 2)
    g_in = _gray_at(img, c[None] - d[..., None] * n_out[None, :, None, :]).mean(0)
    return np.abs(g_in - ref_in[:, None]) <= tol[:, None]


def edge_tracker_for(model, model_path, cam, config, T0: np.ndarray | None = None):
    """``(EdgeTracker, edges used)`` for ``model`` per ``config.edge_source``: ``merged`` (a polyhedral triangle
    mesh tracked with the polygon edges of its planar polygons, :func:`merge_polyhedral_tin`; the tracker's
    ``merge_stats`` say what was merged and its one-off cost), ``polygon`` or ``render``
    (:func:`attach_render_edges`)."""
    from mst.pipeline.tracking.edge_tracker import EdgeTracker

    t0 = time.process_time()
    mode = config.edge_source
    if getattr(model, "cylinders", None) or getattr(model, "circles", None):
        model, mode = _with_curved_primitives(model, model_path, mode)
    merged = merge_polyhedral_tin(model, model_path, mode)
    if merged is None:
        tracker = EdgeTracker(model, cam, config)
        return tracker, attach_render_edges(tracker, model, model_path, mode, T0)
    tracker = EdgeTracker(merged, cam, config)
    tracker.merge_stats = {"triangles": len(model.faces), "polygons": merged.n_faces,
                           "merge_cpu_ms": round((time.process_time() - t0) * 1000.0, 1)}
    return tracker, "merged"


def _with_curved_primitives(model, model_path, mode: str):
    """``(model, edge source)`` to track when a ``.cao`` has cylinders or circles (ViSP primitives; see
    :mod:`mst.meshtools.solids`). With render-based edges (``auto`` or ``render``) and cylinders: one triangle
    model of the polygon faces and the cylinders' closed surfaces, so that the render has the cylinders'
    limbs (the contours ViSP tracks) and their end rims, and they hide what lies behind them (hidden lines,
    KLT depths, surface points); a circle that is not a cylinder's end rim is not tracked (logged). With
    polygon edges (or circles without cylinders) the model as it is: its primitives are not tracked (a
    warning names them), and ``mode`` unchanged."""
    from mst.meshtools.model import PolygonModel
    from mst.meshtools.solids import circle_on_cylinder_end

    name = Path(model_path).name
    cyl, circ = model.cylinders, model.circles
    if not cyl or mode == "polygon":
        what = ", ".join(f"{n} {k}" for n, k in ((len(cyl), "cylinder(s)"), (len(circ), "circle(s)")) if n)
        log.warning(f"{name}: {what} not tracked with polygon edges: mst tracks cylinders by render-based edges "
                    "(--edges auto or render) and circles as a cylinder's end rim")
        return model, mode
    loose = [i for i, c in enumerate(circ) if not circle_on_cylinder_end(model, c)]
    if loose:
        log.warning(f"{name}: circle(s) {', '.join(map(str, loose))} not tracked (not the end rim of a cylinder)")
    V, F = mesh_triangles(model, model_path)
    log.info(f"{name}: {len(cyl)} cylinder(s) tracked by their limbs and end rims in render-based edges of the "
             f"whole model ({len(model.faces)} polygon faces and the cylinders as {len(F)} triangles)")
    return PolygonModel(V, list(F)), "render"


def contour_uv(model, model_path, T_cam_model: np.ndarray, camera, budget: int = 3000) -> np.ndarray | None:
    """(N, 2) px: the contour points (edgelets: silhouettes, self-occlusions, creases) of a render of ``model``
    at ``T_cam_model`` seen by ``camera``, for drawing it (``mst init --overlay`` / ``--show-points``); None when
    ``--edges auto`` tracks the model by its polygon edges (those are drawn instead)."""
    if choose_edges(model, model_path, "auto") != "render":
        return None
    V, F = mesh_triangles(model, model_path)
    prov = RenderEdgeProvider(V, F, camera, budget=budget, border_px=0, near_m=1e-3)
    e = prov.render(np.asarray(T_cam_model, np.float64))
    T = np.asarray(T_cam_model, np.float64)
    Xc = rigid(e.X_model, T[:3, :3], T[:3, 3])
    Xc = Xc[Xc[:, 2] > 1e-6]
    K = prov.K
    return np.stack([K[0, 0] * Xc[:, 0] / Xc[:, 2] + K[0, 2], K[1, 1] * Xc[:, 1] / Xc[:, 2] + K[1, 2]], 1)


def attach_render_edges(tracker, model, model_path, mode: str, T0: np.ndarray | None = None) -> str:
    """Resolve ``--edges mode``; for ``render`` give ``tracker`` a :class:`RenderEdgeProvider` and two edge
    passes per frame. Returns the mode used. Raises :class:`mst.InputError` for meshes it cannot use."""
    used = choose_edges(model, model_path, mode)
    if used != "render":
        return used
    V, F = mesh_triangles(model, model_path)
    if T0 is not None:
        c = centre(T0)
        lo, hi = V.min(0), V.max(0)
        ext = float(np.ptp(V, axis=0).max())
        if (c > lo).all() and (c < hi).all() and ext > 50.0:
            raise InputError(model_path, f"the initial camera is inside the model, which spans {ext:.4g} units: "
                                         "is the model in millimetres? mst expects metres (scale it by 0.001)")
    cfg = tracker.cfg
    curved = curved_fraction(V, F) > CURVED_SHARE
    # the tracker's near plane: the configured one, else relative to the scene depth at the first pose
    near_m = tracker.near(T0) if T0 is not None else (cfg.near_clip_m if cfg.near_clip_m is not None else 1e-3)
    tracker.sample_provider = RenderEdgeProvider(V, F, tracker.cam, crease_deg=40.0, near_m=near_m,
                                                 border_px=cfg.mask_px // 2 + 1)
    # the second pass samples the contour near the frame's pose; a curved mesh's rims take the narrow mask
    tracker.sample_provider.curved = curved
    tracker.sample_provider.extra_passes = EXTRA_PASSES if curved else 0
    tracker.cfg = cfg.replace(passes=max(cfg.passes, 2), mask_px=RENDER_MASK_PX if curved else cfg.mask_px)
    log.info(f"render-based edges ({len(F)} triangles, {'curved' if curved else 'polyhedral'}): edgelets "
             f"from CPU renders at 1/{round(1 / tracker.sample_provider.scale)} resolution")
    return used
