"""The synth scene: the model's triangles, face colours and corners, the clicks, the depth sensor
model, and :func:`build_scene` (camera + scenario + textured mesh + shaded renderer; the
benchmarks use it too)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from mst import InputError, MstError
from mst.core.camera import Camera
from mst.core.poses import transform_points
from mst.pipeline.render import row_ids
from mst.pipeline.synth.config import CEILING, FLOOR, MODEL, WALL, SynthConfig
from mst.pipeline.synth.scenarios import R_canon_from_up, _resolve, focus_point


def load_model_triangles(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The model as triangles (``mst.meshtools.formats.load_triangles``), checked for emptiness and NaN."""
    from mst.meshtools.formats import load_triangles

    V, F = load_triangles(path)
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    if len(F) == 0 or len(V) < 3:
        raise InputError(path, "model has no triangles")
    if not np.isfinite(V).all():
        raise InputError(path, "model has NaN or infinite coordinates")
    ext = V[np.unique(F)].max(0) - V[np.unique(F)].min(0)
    if np.count_nonzero(ext > 1e-9 * max(float(np.abs(V).max()), 1.0)) < 2:
        raise InputError(path, "degenerate model (all vertices on a line or a point)")
    return V, F


# ---------------------------------------------------------------------------- model face colouring
def plane_ids(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(M,) int plane group of each triangle: same quantised normal and plane offset -> same id."""
    from mst.pipeline.render import face_normals

    n = face_normals(V, F)
    c = V.mean(0) if len(V) else np.zeros(3)
    diag = float(np.linalg.norm(V.max(0) - V.min(0))) or 1.0
    d = np.einsum("ij,ij->i", n, V[F[:, 0]] - c)
    key = np.column_stack([np.round(n * 1e3), np.round(d / (1e-3 * diag))]).astype(np.int64)
    return row_ids(key)


#: closed curved meshes: triangles meeting at less than this dihedral angle share a colour (a smooth patch)
SMOOTH_PATCH_DEG = 20.0


def smooth_patch_ids(V: np.ndarray, F: np.ndarray, pid: np.ndarray) -> np.ndarray:
    """Plane groups of a closed curved mesh merged into smooth patches, else ``pid`` unchanged.

    A tessellated smooth surface (a torus, a vase, a scanned sculpture) has one "plane" per triangle;
    colouring each from the palette made a high-contrast mosaic of facets, foreshortened into thin strips
    parallel to the silhouette (the facets there are seen edge-on): a texture no smooth object has, and
    one that biased every contour measurement by a fraction of a pixel (blob orbit: silhouette edges found
    0.13 px outside the true contour on average, 0.32 px spread). On a *closed* mesh (every edge shared by
    exactly two triangles) whose bent interior edges are mostly smooth (more than 5 % of them under the
    crease angle of 40 deg: the curved-mesh rule of ``--edges auto``), triangles meeting at less than
    ``SMOOTH_PATCH_DEG`` share a group: the object is coloured per smooth patch (a vase's body and its
    caps differ, as planes did), its shading still per face. Polyhedral models and open TINs (terrain)
    keep their per-plane groups: their outputs are unchanged.
    """
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    from mst.pipeline.render import face_normals

    key = np.round(V / (1e-7 * (np.abs(V).max() + 1.0))).astype(np.int64)
    Fw = row_ids(key)[F]
    e = np.sort(np.concatenate([Fw[:, [0, 1]], Fw[:, [1, 2]], Fw[:, [2, 0]]]), axis=1)
    tri = np.tile(np.arange(len(F)), 3)
    eid = row_ids(e)
    count = np.bincount(eid)
    if not len(count) or (count != 2).any():
        return pid  # open or non-manifold: not a closed object
    order = np.argsort(eid, kind="stable")
    a, b = tri[order[0::2]], tri[order[1::2]]
    n = face_normals(V, F)
    ang = np.degrees(np.arccos(np.clip((n[a] * n[b]).sum(1), -1.0, 1.0)))
    bent = ang > 1.0
    if not bent.any() or (ang[bent] < 40.0).mean() <= 0.05:
        return pid
    smooth = ang < SMOOTH_PATCH_DEG
    P = int(pid.max()) + 1
    g = sp.coo_matrix((np.ones(int(smooth.sum())), (pid[a[smooth]], pid[b[smooth]])), shape=(P, P))
    return connected_components(g, directed=False)[1][pid].astype(np.int64)


def face_albedo(V: np.ndarray, F: np.ndarray, lighting, base=(0.80, 0.78, 0.74)) -> np.ndarray:
    """(M, 3) albedo per model triangle so that planes sharing an edge differ in shaded brightness.

    Directional lighting alone cannot separate every pair of adjacent faces (some orientation always
    ties), so each plane gets a grey level from a small palette, chosen greedily (largest planes
    first) to maximise the smallest shaded-brightness difference to its already-coloured neighbours.
    A closed curved mesh is coloured per smooth patch instead of per plane (:func:`smooth_patch_ids`).
    """
    from mst.pipeline.render import _unit, face_normals

    M = len(F)
    pid = smooth_patch_ids(V, F, plane_ids(V, F))
    P = pid.max() + 1
    n = face_normals(V, F)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)
    plane_area = np.bincount(pid, weights=area, minlength=P)
    plane_n = np.zeros((P, 3))
    np.add.at(plane_n, pid, n * area[:, None])
    plane_n /= np.maximum(np.linalg.norm(plane_n, axis=1, keepdims=True), 1e-12)
    shade = np.full(P, lighting.ambient)
    for dvec, k in lighting.lights:
        shade += k * np.maximum(plane_n @ _unit(dvec), 0.0)
    # adjacency of planes through shared (welded) edges
    palette = np.array([1.0, 0.62, 0.86, 0.72, 0.94, 0.67, 0.79, 0.90])
    if P > 20000:  # a large TIN (terrain): per-plane palette pick, no greedy pass
        alb = palette[np.random.default_rng(P).integers(0, len(palette), P)]
        return (alb[pid][:, None] * np.asarray(base)[None, :]).astype(np.float32)
    key = np.round(V / (1e-7 * (np.abs(V).max() + 1.0))).astype(np.int64)
    weld = row_ids(key)
    Fw = weld[F]
    e = np.sort(np.concatenate([Fw[:, [0, 1]], Fw[:, [1, 2]], Fw[:, [2, 0]]]), axis=1)
    tri = np.tile(np.arange(M), 3)
    order = np.lexsort((e[:, 1], e[:, 0]))
    e, tri = e[order], tri[order]
    same = np.all(e[1:] == e[:-1], axis=1)
    a, b = pid[tri[:-1][same]], pid[tri[1:][same]]
    adj_pairs = np.unique(np.sort(np.column_stack([a, b])[a != b], axis=1), axis=0)
    nbrs: list[list[int]] = [[] for _ in range(P)]
    for i, j in adj_pairs.tolist():
        nbrs[i].append(j)
        nbrs[j].append(i)
    alb = np.zeros(P)
    for pl in np.argsort(-plane_area, kind="stable"):
        done = [q for q in nbrs[pl] if alb[q] > 0]
        if not done:
            alb[pl] = palette[0]
            continue
        lum_q = shade[done] * alb[done]
        score = [np.min(np.abs(shade[pl] * c - lum_q)) for c in palette]
        alb[pl] = palette[int(np.argmax(score))]
    return (alb[pid][:, None] * np.asarray(base)[None, :]).astype(np.float32)


# ---------------------------------------------------------------------------- clicks
def model_corners(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Indices of "corner" vertices: where triangles of at least 3 different planes meet
    (falls back to 2, then to all used vertices). Vertices are welded by position first."""
    from mst.pipeline.render import face_normals

    used = np.unique(F)
    key = np.round(V / (1e-6 * (np.abs(V).max() + 1.0))).astype(np.int64)
    weld = row_ids(key)
    n = np.round(face_normals(V, F) * 1e3).astype(np.int64)
    inc_v = weld[F.ravel()]
    inc_n = np.repeat(n, 3, axis=0)
    pk = np.column_stack([inc_v, inc_n])
    pid = row_ids(pk)
    first = np.zeros(pid.max() + 1, np.int64)
    first[pid] = np.arange(len(pid))
    count = np.bincount(inc_v[first], minlength=weld.max() + 1)
    for k in (3, 2):
        c = used[count[weld[used]] >= k]
        if len(c):
            # one representative index per welded position
            _, first = np.unique(weld[c], return_index=True)
            return c[np.sort(first)]
    return used


def choose_clicks(renderer, cam: Camera, T_cam_model: np.ndarray, V: np.ndarray, F: np.ndarray, n: int) -> np.ndarray:
    """Up to ``n`` (>= 4 when possible) visible model corners, spread over the image by farthest-point
    sampling. Returns vertex indices; raises ``MstError`` when fewer than 4 corners are visible."""
    cand = model_corners(V, F)
    margin = 0.03 * min(cam.width, cam.height)
    vis = renderer.visible_points(cam, T_cam_model, V[cand], rel_tol=2e-3, margin_px=margin)
    cand = cand[vis]
    if len(cand) < 4:
        raise MstError(f"only {len(cand)} model corners are visible in frame 0 (need 4 for the clicks file): "
                       "try another seed, distance or scenario")
    uv = cam.project(transform_points(T_cam_model, V[cand]))
    first = int(np.argmax(np.linalg.norm(uv - uv.mean(0), axis=1)))
    chosen = [first]
    dmin = np.linalg.norm(uv - uv[first], axis=1)
    while len(chosen) < min(n, len(cand)):
        k = int(np.argmax(dmin))
        if dmin[k] <= 1.0:
            break
        chosen.append(k)
        dmin = np.minimum(dmin, np.linalg.norm(uv - uv[k], axis=1))
    if len(chosen) < 4:
        raise MstError("fewer than 4 distinct model corners visible in frame 0")
    return cand[chosen]


# ---------------------------------------------------------------------------- sensor models
def kinect_depth(z: np.ndarray, cos_inc: np.ndarray, focal_px: float, rng: np.random.Generator) -> np.ndarray:
    """Structured-light depth from exact z (H, W) metres (0 = none): noise, quantisation, holes (module doc)."""
    import cv2

    valid = z > 0
    sigma = 0.0012 + 0.0019 * (z - 0.4) ** 2
    zn = z + rng.standard_normal(z.shape).astype(np.float32) * sigma.astype(np.float32)
    fb = focal_px * 0.075
    disp = np.where(valid & (zn > 0.05), fb / np.maximum(zn, 0.05), 0.0)
    disp_q = np.round(disp * 8.0) / 8.0
    zq = np.where(disp_q > 0, fb / np.maximum(disp_q, 1e-6), 0.0).astype(np.float32)
    # holes at discontinuities (4-neighbour jump > 5% of z), grown by one pixel
    jump = np.zeros(z.shape, bool)
    dz_x = np.abs(np.diff(z, axis=1)) > 0.05 * np.maximum(z[:, 1:], z[:, :-1])
    dz_y = np.abs(np.diff(z, axis=0)) > 0.05 * np.maximum(z[1:], z[:-1])
    jump[:, 1:] |= dz_x
    jump[:, :-1] |= dz_x
    jump[1:] |= dz_y
    jump[:-1] |= dz_y
    jump = cv2.dilate(jump.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    holes = jump | (cos_inc < math.cos(math.radians(80.0))) | (z < 0.3) | (rng.random(z.shape) < 0.002)
    return np.where(valid & ~holes, zq, 0).astype(np.float32)


def build_scene(scenario: str, cfg: SynthConfig, V: np.ndarray, F: np.ndarray):
    """Camera, resolved scenario, the combined mesh and the shaded renderer."""
    from mst.pipeline.render import Lighting, Material, ShadedRenderer
    from mst.pipeline.textures import Texture

    f = float(cfg.focal_px if cfg.focal_px is not None else 525.0 * cfg.width / 640.0)
    cam = Camera(f, f, (cfg.width - 1) / 2.0, (cfg.height - 1) / 2.0, int(cfg.width), int(cfg.height))
    R_cm = R_canon_from_up(cfg.up)                         # canonical <- model
    Vc = V @ R_cm.T
    used = np.unique(F)
    lo, hi = Vc[used].min(0), Vc[used].max(0)
    scene = _resolve(scenario, cfg, lo, hi, cam, focus=focus_point(Vc, F), Vc=Vc[used])
    rng = np.random.default_rng([int(cfg.seed), 7])
    Vs, Fs, mats, offs = [V], [F], [np.full(len(F), MODEL)], [np.zeros((len(F), 2))]
    off = len(V)
    for qV, qF, m in scene.env:
        Vs.append(qV @ R_cm)                               # canonical -> model frame
        Fs.append(qF + off)
        mats.append(np.full(len(qF), m))
        offs.append(np.repeat(rng.uniform(0, 1000.0, (1, 2)), len(qF), axis=0))
        off += len(qV)
    V_all, F_all = np.concatenate(Vs), np.concatenate(Fs)
    mat_all, off_all = np.concatenate(mats), np.concatenate(offs)
    # textures: about 1.5 texels per pixel at the typical viewing distance
    texel = scene.params["texture_distance"] / (1.5 * f)
    size = int(cfg.texture_size)
    seed = int(cfg.seed)
    floor_kind = "terrain" if scene.scenario in ("flyover", "uav", "fpv") else cfg.floor
    recipes = {  # material -> (texture kind, texel size, seed); generated only when the scene uses it
        FLOOR: (floor_kind, texel, seed),
        WALL: ("brick", texel, seed + 1),
        CEILING: ("plaster", texel * 1.5, seed + 2),
    }
    if cfg.model_texture:
        recipes[MODEL] = ("plaster", texel, seed + 3)
    used_mats = {}
    for m in sorted(set(np.unique(mat_all).tolist())):
        if m in recipes:
            kind, tx, sd = recipes[m]
            used_mats[m] = Material(texture=Texture.generate(kind, size, tx, sd))
        else:
            used_mats[m] = Material(albedo=(0.80, 0.78, 0.74))
    lighting = Lighting()
    albedo = np.ones((len(F_all), 3), np.float32)
    if not cfg.model_texture:
        # lights are given in the canonical frame: colour the model's planes there
        albedo[: len(F)] = face_albedo(Vc, F, lighting)
    renderer = ShadedRenderer(V_all, F_all, mat_all, used_mats, lighting, uv_offset_m=off_all, R_tex_model=R_cm,
                              nthreads=cfg.nthreads, albedo_tri=albedo)
    return cam, R_cm, scene, renderer, (V_all, F_all, mat_all)
