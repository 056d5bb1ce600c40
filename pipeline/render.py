"""CPU raycasting renderer (Open3D ``RaycastingScene``, Embree): depth, face ids, shaded colour.

Conventions (mst-wide): the camera frame is x right, y down, z forward; pixel ``(u, v)`` with
integer coordinates is the *centre* of a pixel and a camera point projects to
``u = fx * x / z + cx``, ``v = fy * y / z + cy``. Rays are built here with numpy (Open3D's
``create_rays_pinhole`` puts pixel centres at ``u + 0.5``), with camera-frame directions
``((u - cx) / fx, (v - cy) / fy, 1)``, so the ray parameter ``t`` of a hit *is* its camera z-depth
in metres. Poses: ``T_cam_model`` (4x4, ViSP's cMo) maps model-frame points to the camera frame.
The scene mesh is given in the model frame (metres); internally it is shifted by ``origin`` (its
bounding-box centre) before the float32 conversion, so georeferenced coordinates (hundreds of
kilometres) keep millimetre precision.

Reusable pieces for other stages::

    r = Renderer(V, F)                          # model-frame triangles
    depth = r.render_depth(cam, T_cam_model)    # (H, W) float32 metres, 0 where no surface
    ids = r.render_face_ids(cam, T_cam_model)   # (H, W) int64 triangle index, -1 where none
    vis = r.visible_points(cam, T_cam_model, X_model)   # occlusion test of 3D points

:class:`ShadedRenderer` adds materials (flat albedo or a procedural :class:`~mst.pipeline.textures.Texture`
looked up from the 3D hit point), Lambertian lighting with ambient, a sky, and anti-aliasing by
supersampling only the pixels on a silhouette or crease (where the hit plane or material differs
from a neighbour's), 16 sub-pixel rays each by default. Its primary visibility casts a stride-2
grid and fills 2x2 cells whose corners see one plane with the exact ray-plane depth
(:meth:`ShadedRenderer.primary_hits`), which halves the ray count on planar scenes.

Speed (``mst.eval.bench_synth``, 640x480 orbit of the sample house, colour + depth, 16-sample edge
AA): 60-70 ms of CPU per frame on one thread of this project's shared, loaded 2-core machine
(59 ms with 8 edge samples; ray casting ~15 ms of it, shading and texture lookups most of the rest).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mst.pipeline.camera import Camera

INVALID = np.uint32(0xFFFFFFFF)

#: sub-pixel sample offsets (pixels, relative to the pixel centre) of a 16-sample rank-1 lattice:
#: every sample has its own column and row, so near-horizontal and near-vertical edges get 1/16 coverage steps.
AA_PATTERN_16 = np.array([[(i + 0.5) / 16 - 0.5, ((7 * i) % 16 + 0.5) / 16 - 0.5] for i in range(16)])
AA_PATTERN_8 = np.array([[(i + 0.5) / 8 - 0.5, ((3 * i) % 8 + 0.5) / 8 - 0.5] for i in range(8)])
AA_PATTERN_4 = np.array([[-0.375, -0.125], [0.125, -0.375], [0.375, 0.125], [-0.125, 0.375]])


def aa_pattern(n: int) -> np.ndarray:
    """(n, 2) sub-pixel offsets for ``n`` in {4, 8, 16} (rotated grid / rank-1 lattices)."""
    pats = {4: AA_PATTERN_4, 8: AA_PATTERN_8, 16: AA_PATTERN_16}
    if n not in pats:
        raise ValueError(f"anti-aliasing samples must be 0, 4, 8 or 16, got {n}")
    return pats[n]


def face_normals(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """(M, 3) unit normals (right-hand rule on F's winding), float64; zero rows for degenerate triangles."""
    V = np.asarray(V, np.float64)
    n = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    ln = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, ln, out=np.zeros_like(n), where=ln > 0)


def row_ids(key: np.ndarray) -> np.ndarray:
    """(N,) int64 group id of each row of an integer (N, k) array: equal rows -> equal ids (ids follow
    the rows' lexicographic order). A faster ``np.unique(key, axis=0, return_inverse=True)[1]``."""
    key = np.asarray(key)
    n = len(key)
    if n == 0:
        return np.zeros(0, np.int64)
    order = np.lexsort(key.T[::-1])
    k = key[order]
    new = np.ones(n, bool)
    new[1:] = np.any(k[1:] != k[:-1], axis=1)
    ids = np.empty(n, np.int64)
    ids[order] = np.cumsum(new) - 1
    return ids


def pixel_grid(width: int, height: int) -> np.ndarray:
    """(H*W, 2) float64 pixel-centre coordinates ``(u, v)``, row-major."""
    v, u = np.mgrid[0:height, 0:width]
    return np.stack([u.ravel(), v.ravel()], axis=1).astype(np.float64)


def _rot(R: np.ndarray, x, y, z) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rotate column arrays (x, y, z) by the 3x3 ``R`` (float32 results); ``z`` may be a scalar."""
    R = np.asarray(R, np.float32)
    return tuple(R[i, 0] * x + R[i, 1] * y + R[i, 2] * z for i in range(3))


class Renderer:
    """Ray casting against one triangle mesh given in the model frame.

    Parameters
    ----------
    V : (N, 3) float64 vertices, model frame, metres.
    F : (M, 3) int triangle indices.
    origin : (3,) shift applied before the float32 conversion (default: bounding-box centre).
    nthreads : Embree threads for ``cast_rays`` (0 = all cores).
    """

    def __init__(self, V: np.ndarray, F: np.ndarray, origin: np.ndarray | None = None, nthreads: int = 0):
        import open3d as o3d

        self.V = np.ascontiguousarray(V, dtype=np.float64).reshape(-1, 3)
        self.F = np.ascontiguousarray(F, dtype=np.int64).reshape(-1, 3)
        if len(self.F) == 0:
            raise ValueError("no triangles to render")
        self.origin = (0.5 * (self.V.min(0) + self.V.max(0))) if origin is None else np.asarray(origin, np.float64)
        self.nthreads = int(nthreads)
        self.normals = face_normals(self.V, self.F)
        self._o3d = o3d
        self.scene = o3d.t.geometry.RaycastingScene()
        vl = o3d.core.Tensor(np.ascontiguousarray(self.V - self.origin, dtype=np.float32))
        fl = o3d.core.Tensor(np.ascontiguousarray(self.F, dtype=np.uint32))
        self.scene.add_triangles(vl, fl)
        self._dir_cache: dict = {}

    # ------------------------------------------------------------------ rays
    def camera_dirs(self, cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera-frame ray directions of all pixel centres, row-major, z = 1: ``(x, y, 1/|d|)`` float32 (H*W,) each.

        Cached for the last camera.
        """
        key = (cam.fx, cam.fy, cam.cx, cam.cy, tuple(cam.dist.tolist()), cam.width, cam.height)
        c = self._dir_cache.get(key)
        if c is None:
            xy = cam.unproject(pixel_grid(cam.width, cam.height))
            x, y = xy[:, 0].astype(np.float32), xy[:, 1].astype(np.float32)
            c = (x, y, (1.0 / np.sqrt(1.0 + xy[:, 0] ** 2 + xy[:, 1] ** 2)).astype(np.float32))
            self._dir_cache = {key: c}
        return c

    def rays_for(self, T_cam_model: np.ndarray, x_cam, y_cam, z_cam=1.0):
        """Camera-frame directions (column arrays) -> (local-frame origin (3,) float64, model-frame (dx, dy, dz))."""
        T = np.asarray(T_cam_model, np.float64)
        R_model_cam = T[:3, :3].T
        c_model = -R_model_cam @ T[:3, 3]
        return c_model - self.origin, _rot(R_model_cam, x_cam, y_cam, z_cam)

    def cast(self, origin_local: np.ndarray, d: tuple) -> tuple[np.ndarray, np.ndarray]:
        """Cast rays from one local-frame origin along model-frame directions ``d = (dx, dy, dz)``.

        Returns ``t`` (N,) float32 (inf on miss) and triangle ids (N,) uint32 (``INVALID`` on miss).
        With camera-frame directions of unit z, ``t`` is the camera z-depth (metres).
        """
        n = len(d[0])
        rays = np.empty((n, 6), np.float32)
        rays[:, :3] = origin_local
        rays[:, 3], rays[:, 4], rays[:, 5] = d
        ans = self.scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays), nthreads=self.nthreads)
        return ans["t_hit"].numpy(), ans["primitive_ids"].numpy()

    # ------------------------------------------------------------------ geometry products
    def render_depth_ids(self, cam: Camera, T_cam_model: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depth (H, W) float32 metres (0 = no surface) and triangle ids (H, W) int64 (-1 = none)."""
        x, y, _ = self.camera_dirs(cam)
        o, d = self.rays_for(T_cam_model, x, y)
        t, prim = self.cast(o, d)
        hit = prim != INVALID
        depth = np.where(hit, t, 0).astype(np.float32).reshape(cam.height, cam.width)
        ids = np.where(hit, prim.astype(np.int64), -1).reshape(cam.height, cam.width)
        return depth, ids

    def render_depth(self, cam: Camera, T_cam_model: np.ndarray) -> np.ndarray:
        """(H, W) float32 camera z-depth in metres, 0 where the ray hits nothing."""
        return self.render_depth_ids(cam, T_cam_model)[0]

    def render_face_ids(self, cam: Camera, T_cam_model: np.ndarray) -> np.ndarray:
        """(H, W) int64 index of the triangle seen at each pixel centre, -1 where none."""
        return self.render_depth_ids(cam, T_cam_model)[1]

    def visible_points(self, cam: Camera, T_cam_model: np.ndarray, X_model: np.ndarray, rel_tol: float = 1e-3,
                       margin_px: float = 0.0) -> np.ndarray:
        """(N,) bool: point in front of the camera, inside the image (minus ``margin_px``) and not hidden.

        A point is hidden when a surface is hit before ``(1 - rel_tol)`` of its depth along its ray.
        Points lying on a surface (model vertices) count as visible.
        """
        T = np.asarray(T_cam_model, np.float64)
        X = np.asarray(X_model, np.float64).reshape(-1, 3)
        Xc = X @ T[:3, :3].T + T[:3, 3]
        z = Xc[:, 2]
        ok = z > 1e-9
        out = np.zeros(len(X), bool)
        if not ok.any():
            return out
        uv = cam.project(Xc[ok])
        inside = ((uv[:, 0] >= -0.5 + margin_px) & (uv[:, 0] <= cam.width - 0.5 - margin_px)
                  & (uv[:, 1] >= -0.5 + margin_px) & (uv[:, 1] <= cam.height - 0.5 - margin_px))
        o, d = self.rays_for(T, Xc[ok, 0] / z[ok], Xc[ok, 1] / z[ok])
        if np.ndim(d[2]) == 0:
            d = (d[0], d[1], np.full(len(d[0]), d[2], np.float32))
        t, _ = self.cast(o, d)
        out[np.nonzero(ok)[0]] = inside & (t >= z[ok] * (1 - rel_tol))
        return out


# ---------------------------------------------------------------------------- shading
@dataclass
class Material:
    """Flat ``albedo`` (RGB in [0, 1]) or a texture (its colour, times an optional large-scale modulation)."""

    albedo: tuple[float, float, float] = (0.8, 0.8, 0.8)
    texture: object | None = None  # mst.pipeline.textures.Texture
    modulation: object | None = None


def _unit(v) -> np.ndarray:
    v = np.asarray(v, np.float64)
    return v / np.linalg.norm(v)


@dataclass
class Lighting:
    """Ambient + directional Lambertian lights, directions given in the *texture frame* (z up), pointing to the light."""

    ambient: float = 0.22
    lights: list[tuple[tuple[float, float, float], float]] = field(default_factory=lambda: [
        ((0.45, -0.35, 0.82), 0.62),   # key light (sun, high)
        ((-0.70, 0.55, 0.30), 0.30),   # fill light from the other side
    ])
    sky_zenith: tuple[float, float, float] = (0.42, 0.62, 0.90)
    sky_horizon: tuple[float, float, float] = (0.85, 0.90, 0.95)


#: rotation/scale of the modulation lookup relative to the main texture (breaks its tile period)
_MOD_ROT = np.array([[0.8, 0.6], [-0.6, 0.8]]) * 0.173


class ShadedRenderer(Renderer):
    """A :class:`Renderer` with per-triangle materials, lighting and edge-only anti-aliasing.

    Parameters
    ----------
    material_ids : (M,) int per triangle, keys of ``materials``.
    materials : material id -> :class:`Material`.
    albedo_tri : (M, 3) per-triangle albedo of flat (untextured) materials, overriding ``Material.albedo``.
    uv_offset_m : (M, 2) per-triangle texture offsets (metres), decorrelating surfaces that share a texture.
    R_tex_model : 3x3 rotation from the model frame to the texture frame (z up there: walls get
        horizontal brick courses, the sky's zenith is +z). Textures are planar projections of the
        hit point on the two texture-frame axes most parallel to the triangle.
    """

    def __init__(self, V, F, material_ids, materials: dict[int, Material], lighting: Lighting | None = None,
                 uv_offset_m: np.ndarray | None = None, R_tex_model: np.ndarray | None = None,
                 origin: np.ndarray | None = None, nthreads: int = 0, albedo_tri: np.ndarray | None = None):
        super().__init__(V, F, origin=origin, nthreads=nthreads)
        M = len(self.F)
        self.material_ids = np.asarray(material_ids, np.int64).reshape(-1)
        if len(self.material_ids) != M:
            raise ValueError("one material id per triangle needed")
        missing = set(np.unique(self.material_ids).tolist()) - set(materials)
        if missing:
            raise ValueError(f"material ids without a material: {sorted(missing)}")
        self.materials = materials
        mids = np.array(sorted(materials), np.int64)
        mat_index = np.searchsorted(mids, self.material_ids)          # position of each triangle's material
        self.lighting = lighting or Lighting()
        self.R_tex_model = np.eye(3) if R_tex_model is None else np.asarray(R_tex_model, np.float64)
        uv_off = np.zeros((M, 2)) if uv_offset_m is None else np.asarray(uv_offset_m, np.float64).reshape(M, 2)
        L = self.lighting
        self._light_dirs_model = np.array([self.R_tex_model.T @ _unit(d) for d, _ in L.lights]).reshape(-1, 3)
        self._light_k = np.array([k for _, k in L.lights], np.float64)
        self._sky_row = self.R_tex_model[2].astype(np.float32)  # texture-frame up, in model coordinates
        n = self.normals
        self._n32 = tuple(np.ascontiguousarray(n[:, i], dtype=np.float32) for i in range(3))
        self._v0_local = self.V[self.F[:, 0]] - self.origin
        # plane groups for the edge test: same plane (normal, offset) and same material -> same id
        diag = float(np.linalg.norm(self.V.max(0) - self.V.min(0))) or 1.0
        dpl = np.einsum("ij,ij->i", n, self._v0_local)
        key = np.column_stack([np.round(n * 1e4), np.round(dpl / (1e-4 * diag)), self.material_ids]).astype(np.int64)
        self._plane_id = np.concatenate([row_ids(key).astype(np.int32), [-1]])  # entry M: no hit
        self._plane_h = dpl  # plane offset n . X (local frame) of each triangle, float64
        # texture mapping per triangle: u = a_u . P_model + off_u (metres), same for v
        n_tex = n @ self.R_tex_model.T
        axis = np.argmax(np.abs(n_tex), axis=1)
        e = np.eye(3)
        sel_u = np.where(axis[:, None] == 0, e[1], e[0])           # axis x -> u = y ; else u = x
        sel_v = np.where(axis[:, None] == 2, e[1], -e[2])          # axis z -> v = y ; else v = -z
        self._a_u = sel_u @ self.R_tex_model                         # model-frame linear forms
        self._a_v = sel_v @ self.R_tex_model
        self._c_u = self._a_u @ self.origin + uv_off[:, 0]          # constants for local-frame points
        self._c_v = self._a_v @ self.origin + uv_off[:, 1]
        self._a_cols = tuple(np.ascontiguousarray(a[:, i], dtype=np.float32) for a in (self._a_u, self._a_v) for i in range(3))
        tex_ids = sorted(k for k, m in materials.items() if m.texture is not None)
        self._tex_list = [materials[k] for k in tex_ids]
        lut = {k: i for i, k in enumerate(tex_ids)}
        lut_arr = np.array([lut.get(int(k), -1) for k in mids], np.int64)
        self._tex_mat = np.concatenate([lut_arr[mat_index], [-1]])
        self._albedo = np.array([materials[int(k)].albedo for k in mids], np.float32).reshape(-1, 3)[mat_index]
        if albedo_tri is not None:  # per-triangle flat colours (e.g. a face colouring of the model)
            self._albedo = np.asarray(albedo_tri, np.float32).reshape(M, 3)

    # ------------------------------------------------------------------ per-ray shading
    def _frame_tables(self, origin_local: np.ndarray) -> dict:
        """Per-triangle quantities of one camera position: two-sided shading, flat colours, uv origins."""
        n = self.normals
        facing = np.einsum("ij,ij->i", n, origin_local - self._v0_local) >= 0
        n_eff = np.where(facing[:, None], n, -n)
        shade = np.full(len(n), self.lighting.ambient)
        for ld, k in zip(self._light_dirs_model, self._light_k):
            shade += k * np.maximum(n_eff @ ld, 0.0)
        return {
            "shade": shade.astype(np.float32),
            "flat": np.concatenate([self._albedo * shade[:, None], np.zeros((1, 3))]).astype(np.float32),
            "u0": self._a_u @ origin_local + self._c_u,  # metres, float64
            "v0": self._a_v @ origin_local + self._c_v,
        }

    def shade(self, origin_local: np.ndarray, d: tuple, inv_norm: np.ndarray, t: np.ndarray, prim: np.ndarray,
              focal_px: float, tables: dict | None = None) -> np.ndarray:
        """Colour (N, 3) float32 linear RGB in [0, 1] of rays from one origin along ``d = (dx, dy, dz)``.

        ``inv_norm``: 1/|d| per ray; ``t``/``prim``: the cast result.
        """
        tb = tables or self._frame_tables(origin_local)
        M = len(self.F)
        dx, dy, dz = d
        pc = np.minimum(prim, M).astype(np.int64)  # M = no hit
        rgb = np.take(tb["flat"], pc, axis=0)
        miss = np.flatnonzero(pc == M)
        L = self.lighting
        if len(miss):
            r = self._sky_row
            el = np.clip((r[0] * dx[miss] + r[1] * dy[miss] + r[2] * dz[miss]) * inv_norm[miss], 0, 1)[:, None]
            hz, zn = np.asarray(L.sky_horizon, np.float32), np.asarray(L.sky_zenith, np.float32)
            rgb[miss] = hz + (zn - hz) * el
        tmat = self._tex_mat[pc]  # texture-material index per ray, -1 = flat or miss
        counts = np.bincount(tmat + 1, minlength=len(self._tex_list) + 1)
        for k in np.nonzero(counts[1:])[0]:
            m = self._tex_list[k]
            sel = np.flatnonzero(tmat == k)
            p = pc[sel]
            tt = t[sel]
            ddx, ddy, ddz = dx[sel], dy[sel], dz[sel]
            tex = m.texture
            inv_tex = np.float32(1.0 / tex.texel_m)
            period = tex.size * tex.texel_m
            au0, au1, au2, av0, av1, av2 = self._a_cols
            u0 = np.mod(tb["u0"], period).astype(np.float32)  # wrapped per triangle (precision)
            v0 = np.mod(tb["v0"], period).astype(np.float32)
            um = u0[p] + tt * (au0[p] * ddx + au1[p] * ddy + au2[p] * ddz)
            vm = v0[p] + tt * (av0[p] * ddx + av1[p] * ddy + av2[p] * ddz)
            nx, ny, nz = self._n32
            cosi = np.abs(nx[p] * ddx + ny[p] * ddy + nz[p] * ddz) * inv_norm[sel]
            foot_m = tt * np.float32(1.0 / focal_px) / np.sqrt(np.maximum(cosi, np.float32(0.05)))
            col = tex.sample(um * inv_tex, vm * inv_tex, foot_m * inv_tex)
            if m.modulation is not None:
                mt = m.modulation
                R = _MOD_ROT.astype(np.float32) * np.float32(1.0 / mt.texel_m)
                col *= mt.sample_level0(R[0, 0] * um + R[0, 1] * vm, R[1, 0] * um + R[1, 1] * vm)
            col *= tb["shade"][p][:, None]
            rgb[sel] = col
        return rgb

    # ------------------------------------------------------------------ images
    def edge_mask(self, prim: np.ndarray, t: np.ndarray, shape: tuple[int, int], crease_deg: float = 3.0,
                  rel_depth_jump: float = 0.02) -> np.ndarray:
        """(H, W) bool: pixels on a silhouette or crease, to be supersampled.

        A pixel and one of its 8 neighbours are separated by an edge when they see different planes
        (plane id: normal, offset, material) and, further, one of them sees nothing, the materials
        differ, the normals differ by more than ``crease_deg``, or the depth jumps by more than
        ``rel_depth_jump`` (relative). Gentle creases of a terrain TIN are not edges.
        """
        H, W = shape
        M = len(self.F)
        pc = np.minimum(prim, M).astype(np.int64).reshape(H, W)
        pl = self._plane_id[pc]
        tt = np.asarray(t, np.float32).reshape(H, W)
        nx, ny, nz = self._n32
        mat = np.concatenate([self.material_ids, [-1]])
        cos_tol = np.float32(np.cos(np.radians(crease_deg)))
        edge = np.zeros((H, W), bool)
        for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
            ys0, ys1 = slice(0, H - dy), slice(dy, H)
            xs0, xs1 = (slice(0, W - dx), slice(dx, W)) if dx >= 0 else (slice(-dx, W), slice(0, W + dx))
            ya, xa = np.nonzero(pl[ys0, xs0] != pl[ys1, xs1])
            if not len(ya):
                continue
            yb, xb = ya + dy, xa + (dx if dx >= 0 else 0)
            xa = xa + (0 if dx >= 0 else -dx)
            pa, pb = pc[ya, xa], pc[yb, xb]
            miss = (pa == M) | (pb == M)
            pa0, pb0 = np.where(miss, 0, pa), np.where(miss, 0, pb)
            cosn = nx[pa0] * nx[pb0] + ny[pa0] * ny[pb0] + nz[pa0] * nz[pb0]
            ta, tb = tt[ya, xa], tt[yb, xb]
            jump = np.abs(ta - tb) > np.float32(rel_depth_jump) * np.minimum(ta, tb)
            sep = miss | (mat[pa] != mat[pb]) | (np.abs(cosn) < cos_tol) | jump
            edge[ya[sep], xa[sep]] = True
            edge[yb[sep], xb[sep]] = True
        return edge

    def primary_hits(self, cam: Camera, o: np.ndarray, d: tuple) -> tuple[np.ndarray, np.ndarray]:
        """Hits of all pixel-centre rays, casting only where needed.

        Rays are cast on a stride-2 grid of pixels first. Inside a 2x2 cell of those samples that all
        see the same plane (plane id: normal, offset, material), the other pixels see that plane too:
        their depth is the exact ray-plane intersection and their triangle id a triangle of that
        plane. Cells whose corners all miss are sky. Every other pixel is cast. (A feature thinner than
        two pixels lying entirely between the coarse samples can be lost; larger ones are exact.)
        Returns ``t`` (H*W,) float32 (inf on miss) and triangle ids (H*W,) uint32.
        """
        H, W = cam.height, cam.width
        ys = np.arange(0, H, 2)
        xs = np.arange(0, W, 2)
        if ys[-1] != H - 1:
            ys = np.append(ys, H - 1)
        if xs[-1] != W - 1:
            xs = np.append(xs, W - 1)
        cidx = (ys[:, None] * W + xs[None, :]).ravel()
        tc, pcst = self.cast(o, (d[0][cidx], d[1][cidx], d[2][cidx]))
        M = len(self.F)
        plc = self._plane_id[np.minimum(pcst, M).astype(np.int64)].reshape(len(ys), len(xs))
        same = ((plc[:-1, :-1] == plc[1:, :-1]) & (plc[:-1, :-1] == plc[:-1, 1:]) & (plc[:-1, :-1] == plc[1:, 1:]))
        # cell of each pixel: rows ys[k] <= i <= ys[k+1] (k = i // 2, the last odd row in the last cell)
        ki = np.minimum(np.arange(H) // 2, len(ys) - 2)
        kj = np.minimum(np.arange(W) // 2, len(xs) - 2)
        rep2 = pcst.reshape(len(ys), len(xs))[:-1, :-1]      # each cell's top-left sample
        if H % 2 == 0 and W % 2 == 0:                         # cells of 2x2 pixels: plain repeats
            uni = np.repeat(np.repeat(same, 2, axis=0), 2, axis=1).ravel()
            rep = np.repeat(np.repeat(rep2, 2, axis=0), 2, axis=1).ravel()
        else:
            uni = same[ki][:, kj].ravel()
            rep = rep2[ki][:, kj].ravel()
        t = np.empty(H * W, np.float32)
        prim = np.empty(H * W, np.uint32)
        # uniform cells: analytic depth on the plane of the representative triangle
        ui = np.flatnonzero(uni)
        pr = rep[ui]
        hit = pr != INVALID
        uh, um = ui[hit], ui[~hit]
        p64 = pr[hit].astype(np.int64)
        nx, ny, nz = self._n32
        num_tri = (self._plane_h - self.normals @ o).astype(np.float32)  # per triangle, float64 then rounded
        num = num_tri[p64]
        den = nx[p64] * d[0][uh] + ny[p64] * d[1][uh] + nz[p64] * d[2][uh]
        t[uh] = num / den
        prim[uh] = pr[hit]
        t[um] = np.inf
        prim[um] = INVALID
        # the rest: cast
        ci = np.flatnonzero(~uni)
        if len(ci):
            t[ci], prim[ci] = self.cast(o, (d[0][ci], d[1][ci], d[2][ci]))
        return t, prim

    def render(self, cam: Camera, T_cam_model: np.ndarray, aa_samples: int = 16, with_cos: bool = False,
               full_cast: bool = False) -> dict:
        """Render one view (``full_cast``: cast every pixel instead of :meth:`primary_hits`).

        Returns a dict with ``rgb`` (H, W, 3) float32 linear colour in [0, 1] (edge pixels averaged over
        ``aa_samples`` sub-pixel rays), ``depth`` (H, W) float32 camera z-depth in metres of the pixel-centre
        ray (0 = no surface), ``ids`` (H, W) int64 triangle ids (-1 = none), ``edges`` (H, W) bool
        (supersampled pixels), ``n_edge_px``, and with ``with_cos`` ``cos_incidence`` (H, W) float32
        |cos| of the angle between ray and surface normal (0 = no surface).
        """
        H, W = cam.height, cam.width
        x, y, inv_norm = self.camera_dirs(cam)
        o, d = self.rays_for(T_cam_model, x, y)
        if full_cast or H < 4 or W < 4:
            t, prim = self.cast(o, d)
        else:
            t, prim = self.primary_hits(cam, o, d)
        focal = 0.5 * (cam.fx + cam.fy)
        tables = self._frame_tables(o)
        rgb = self.shade(o, d, inv_norm, t, prim, focal, tables)
        edges = np.zeros((H, W), bool)
        if aa_samples:
            edges = self.edge_mask(prim, t, (H, W))
            e_idx = np.flatnonzero(edges)
            if len(e_idx):
                pat = aa_pattern(aa_samples)
                uv = np.stack([e_idx % W, e_idx // W], axis=1).astype(np.float64)
                sub = (uv[:, None, :] + pat[None, :, :]).reshape(-1, 2)
                xy = cam.unproject(sub)
                sx, sy = xy[:, 0].astype(np.float32), xy[:, 1].astype(np.float32)
                s_inv = (1.0 / np.sqrt(1.0 + sx.astype(np.float64) ** 2 + sy.astype(np.float64) ** 2)).astype(np.float32)
                o2, d2 = self.rays_for(T_cam_model, sx, sy)
                t2, p2 = self.cast(o2, d2)
                c2 = self.shade(o2, d2, s_inv, t2, p2, focal, tables)
                rgb[e_idx] = c2.reshape(len(e_idx), len(pat), 3).mean(axis=1)
        hit = prim != INVALID
        out = {
            "rgb": rgb.reshape(H, W, 3),
            "depth": np.where(hit, t, 0).astype(np.float32).reshape(H, W),
            "ids": np.where(hit, prim.astype(np.int64), -1).reshape(H, W),
            "edges": edges,
            "n_edge_px": int(edges.sum()),
        }
        if with_cos:
            pc = np.where(hit, prim, 0).astype(np.int64)
            nx, ny, nz = self._n32
            cosi = np.abs(nx[pc] * d[0] + ny[pc] * d[1] + nz[pc] * d[2]) * inv_norm
            out["cos_incidence"] = np.where(hit, cosi, 0).astype(np.float32).reshape(H, W)
        return out


def render_depth(V: np.ndarray, F: np.ndarray, cam: Camera, T_cam_model: np.ndarray) -> np.ndarray:
    """One-shot depth image (H, W) float32 metres of mesh ``(V, F)`` (model frame); 0 = no surface."""
    return Renderer(V, F).render_depth(cam, T_cam_model)


def render_face_ids(V: np.ndarray, F: np.ndarray, cam: Camera, T_cam_model: np.ndarray) -> np.ndarray:
    """One-shot triangle-id image (H, W) int64 of mesh ``(V, F)``; -1 = no surface."""
    return Renderer(V, F).render_face_ids(cam, T_cam_model)
