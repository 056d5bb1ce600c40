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
(:meth:`ShadedRenderer.primary_hits`), which quarters the ray count on planar scenes. Per-ray work
(ray building, cell filling, edge test, shading with mip-mapped texture lookups, the sub-pixel
mean) runs in single-threaded numba kernels (:mod:`mst.pipeline.render_kernels`, float32, compiled
once and cached on disk), so the only multi-threaded part is Embree (``nthreads``).

Speed (``mst.eval.bench.synth``, 640x480 orbit of the sample house, colour + depth, one thread of
this project's shared 2-core machine): about 41 ms of CPU per frame with 16 edge rays, 35 ms with 8
(ray casting ~18 ms of it, shading ~15 ms); the numpy version before the kernels took 73 ms.

Size (~520 lines): one class hierarchy (:class:`Renderer` and the :class:`ShadedRenderer` built on
its ray set-up) with the materials and lights it shades with; its per-pixel kernels are already
apart (``render_kernels``). Imports numpy, Open3D (lazily), :mod:`mst.core` and ``textures``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mst.core.camera import Camera
from mst.core.poses import matmul_exact, transform_points
from mst.pipeline.tracking.exact import mv

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
        c_model = -mv(R_model_cam, T[:3, 3])
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
        Xc = transform_points(T, X, elementwise=True)
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
        self._light_dirs_model = np.array([mv(self.R_tex_model.T, _unit(d)) for d, _ in L.lights]).reshape(-1, 3)
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
        n_tex = matmul_exact(n, self.R_tex_model.T)
        axis = np.argmax(np.abs(n_tex), axis=1)
        e = np.eye(3)
        sel_u = np.where(axis[:, None] == 0, e[1], e[0])           # axis x -> u = y ; else u = x
        sel_v = np.where(axis[:, None] == 2, e[1], -e[2])          # axis z -> v = y ; else v = -z
        self._a_u = matmul_exact(sel_u, self.R_tex_model)                     # model-frame linear forms
        self._a_v = matmul_exact(sel_v, self.R_tex_model)
        self._c_u = mv(self._a_u, self.origin) + uv_off[:, 0]          # constants for local-frame points
        self._c_v = mv(self._a_v, self.origin) + uv_off[:, 1]
        self._a_cols = tuple(np.ascontiguousarray(a[:, i], dtype=np.float32) for a in (self._a_u, self._a_v) for i in range(3))
        tex_ids = sorted(k for k, m in materials.items() if m.texture is not None)
        self._tex_list = [materials[k] for k in tex_ids]
        lut = {k: i for i, k in enumerate(tex_ids)}
        lut_arr = np.array([lut.get(int(k), -1) for k in mids], np.int64)
        self._tex_mat = np.concatenate([lut_arr[mat_index], [-1]])
        self._albedo = np.array([materials[int(k)].albedo for k in mids], np.float32).reshape(-1, 3)[mat_index]
        if albedo_tri is not None:  # per-triangle flat colours (e.g. a face colouring of the model)
            self._albedo = np.asarray(albedo_tri, np.float32).reshape(M, 3)
        self._build_kernel_tables()

    def _build_kernel_tables(self) -> None:
        """Arrays for the numba kernels: stacked texture atlases (main textures first, then the
        modulations), per-texture constants, per-triangle texture index, float32 normals and uv forms."""
        texs = [m.texture for m in self._tex_list]
        mod_idx = []
        for m in self._tex_list:
            if m.modulation is None:
                mod_idx.append(-1)
            else:
                mod_idx.append(len(texs))
                texs.append(m.modulation)
        K = max(len(texs), 1)
        if texs:
            hmax = max(t.atlas.shape[0] for t in texs)
            wmax = max(t.atlas.shape[1] for t in texs)
            lmax = max(len(t.levels) for t in texs)
        else:
            hmax = wmax = lmax = 1
        self._k_atlas = np.zeros((K, hmax, wmax, 3), np.uint8)
        self._k_level_xy = np.zeros((K, lmax, 2), np.float32)
        self._k_size = np.ones(K, np.int64)
        self._k_inv_texel = np.ones(K, np.float32)
        self._k_nlev = np.ones(K, np.int64)
        self._k_mod_R = np.zeros((K, 2, 2), np.float32)
        for i, tx in enumerate(texs):
            a = tx.atlas
            self._k_atlas[i, : a.shape[0], : a.shape[1]] = a
            self._k_level_xy[i, : len(tx.levels)] = tx.level_xy
            self._k_size[i] = tx.size
            self._k_inv_texel[i] = np.float32(1.0 / tx.texel_m)
            self._k_nlev[i] = len(tx.levels)
        self._k_mod_idx = np.full(K, -1, np.int64)
        for i, (m, mi) in enumerate(zip(self._tex_list, mod_idx)):
            self._k_mod_idx[i] = mi
            if mi >= 0:
                self._k_mod_R[i] = _MOD_ROT.astype(np.float32) * np.float32(1.0 / m.modulation.texel_m)
        M = len(self.F)
        self._k_tex_tri = np.ascontiguousarray(self._tex_mat[:M])
        # uv of the camera centre are wrapped to the tile (float32 precision far from the origin); with a
        # modulation texture (not periodic with the tile) to 1024 tiles, so its seams are kilometres apart
        periods = np.array([m.texture.size * m.texture.texel_m * (1 if m.modulation is None else 1024)
                            for m in self._tex_list] or [1.0], np.float64)
        self._period_tri = np.where(self._k_tex_tri >= 0, periods[np.maximum(self._k_tex_tri, 0)], 1.0)
        self._k_nrm = np.ascontiguousarray(self.normals, dtype=np.float32)
        self._k_a_uv = np.ascontiguousarray(np.column_stack([self._a_u, self._a_v]), dtype=np.float32)
        self._k_mat = np.concatenate([self.material_ids, [-1]]).astype(np.int64)
        L = self.lighting
        self._k_sky = np.array([self._sky_row, L.sky_horizon, L.sky_zenith], np.float32)

    # ------------------------------------------------------------------ per-ray shading
    def _frame_tables(self, origin_local: np.ndarray) -> dict:
        """Per-triangle quantities of one camera position: two-sided shading, flat colours, uv origins
        (metres, float32, wrapped to the tile period of the triangle's texture for precision)."""
        n = self.normals
        facing = np.einsum("ij,ij->i", n, origin_local - self._v0_local) >= 0
        n_eff = np.where(facing[:, None], n, -n)
        shade = np.full(len(n), self.lighting.ambient)
        for ld, k in zip(self._light_dirs_model, self._light_k):
            shade += k * np.maximum(mv(n_eff, ld), 0.0)
        u0 = mv(self._a_u, origin_local) + self._c_u
        v0 = mv(self._a_v, origin_local) + self._c_v
        return {
            "shade": shade.astype(np.float32),
            "flat": np.concatenate([self._albedo * shade[:, None], np.zeros((1, 3))]).astype(np.float32),
            "u0": np.mod(u0, self._period_tri).astype(np.float32),
            "v0": np.mod(v0, self._period_tri).astype(np.float32),
        }

    def shade(self, R_model_cam: np.ndarray, x_cam: np.ndarray, y_cam: np.ndarray, t: np.ndarray, prim: np.ndarray,
              focal_px: float, tables: dict, group: int = 1, inv_norm: np.ndarray | None = None) -> np.ndarray:
        """Colour (N // group, 3) float32 linear RGB in [0, 1] of rays from the camera centre.

        Rays have camera-frame directions ``(x_cam, y_cam, 1)`` (float32 (N,)) rotated to the model
        frame by ``R_model_cam``; ``t``/``prim``: the cast result; ``tables``: :meth:`_frame_tables`
        of the camera centre. Each output row is the mean of ``group`` consecutive rays (sub-pixel samples).
        ``inv_norm``: optional 1/|(x, y, 1)| per ray (computed when absent).
        """
        from mst.pipeline import render_kernels as rk

        n = len(x_cam) // group
        out = np.empty((n, 3), np.float32)
        inv = np.zeros(0, np.float32) if inv_norm is None else np.ascontiguousarray(inv_norm, np.float32)
        rk.shade_rays(np.ascontiguousarray(x_cam, np.float32), np.ascontiguousarray(y_cam, np.float32), inv,
                      np.asarray(R_model_cam, np.float32), np.ascontiguousarray(t, np.float32),
                      np.ascontiguousarray(prim, np.uint32), int(group), tables["flat"], self._k_tex_tri,
                      tables["u0"], tables["v0"], self._k_a_uv, self._k_nrm, tables["shade"], self._k_sky,
                      np.float32(1.0 / focal_px), self._k_atlas, self._k_size, self._k_inv_texel, self._k_nlev,
                      self._k_level_xy, self._k_mod_idx, self._k_mod_R, out)
        return out

    # ------------------------------------------------------------------ images
    def edge_mask(self, prim: np.ndarray, t: np.ndarray, shape: tuple[int, int], crease_deg: float = 3.0,
                  rel_depth_jump: float = 0.02) -> np.ndarray:
        """(H, W) bool: pixels on a silhouette or crease, to be supersampled.

        A pixel and one of its 8 neighbours are separated by an edge when they see different planes
        (plane id: normal, offset, material) and, further, one of them sees nothing, the materials
        differ, the normals differ by more than ``crease_deg``, or the depth jumps by more than
        ``rel_depth_jump`` (relative). Gentle creases of a terrain TIN are not edges.
        """
        from mst.pipeline import render_kernels as rk

        H, W = shape
        M = len(self.F)
        pc = np.minimum(prim, M).astype(np.int64).reshape(H, W)
        tt = np.asarray(t, np.float32).reshape(H, W)
        edge = np.zeros((H, W), bool)
        rk.edge_mask(pc, tt, self._plane_id, self._k_nrm, self._k_mat, np.float32(np.cos(np.radians(crease_deg))),
                     np.float32(rel_depth_jump), edge)
        return edge

    def _cast_idx(self, o: np.ndarray, R32: np.ndarray, x: np.ndarray, y: np.ndarray, idx: np.ndarray):
        """Cast the pixel rays ``idx`` (all when empty) of camera-frame directions ``(x, y, 1)``."""
        from mst.pipeline import render_kernels as rk

        n = len(idx) if len(idx) else len(x)
        rays = np.empty((n, 6), np.float32)
        rk.build_rays(np.asarray(o, np.float32), R32, x, y, idx, rays)
        ans = self.scene.cast_rays(self._o3d.core.Tensor.from_numpy(rays), nthreads=self.nthreads)
        return ans["t_hit"].numpy(), ans["primitive_ids"].numpy()

    def primary_hits(self, cam: Camera, o: np.ndarray, R_model_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Hits of all pixel-centre rays (from local-frame centre ``o``), casting only where needed.

        Rays are cast on a stride-2 grid of pixels first. Inside a 2x2 cell of those samples that all
        see the same plane (plane id: normal, offset, material), the other pixels see that plane too:
        their depth is the exact ray-plane intersection and their triangle id a triangle of that
        plane. Cells whose corners all miss are sky. Every other pixel is cast. (A feature thinner than
        two pixels lying entirely between the coarse samples can be lost; larger ones are exact.)
        Returns ``t`` (H*W,) float32 (inf on miss) and triangle ids (H*W,) uint32.
        """
        from mst.pipeline import render_kernels as rk

        H, W = cam.height, cam.width
        x, y, _ = self.camera_dirs(cam)
        R32 = np.asarray(R_model_cam, np.float32)
        ys = np.arange(0, H, 2)
        xs = np.arange(0, W, 2)
        if ys[-1] != H - 1:
            ys = np.append(ys, H - 1)
        if xs[-1] != W - 1:
            xs = np.append(xs, W - 1)
        cidx = (ys[:, None] * W + xs[None, :]).ravel()
        _, pcst = self._cast_idx(o, R32, x, y, cidx)
        num_tri = (self._plane_h - mv(self.normals, o)).astype(np.float32)  # per triangle, float64 then rounded
        t = np.empty(H * W, np.float32)
        prim = np.empty(H * W, np.uint32)
        rest = np.empty(H * W, np.int64)
        n_rest = rk.fill_planar_cells(H, W, ys, xs, np.ascontiguousarray(pcst.reshape(len(ys), len(xs))),
                                      self._plane_id, num_tri, self._k_nrm, R32, x, y, t, prim, rest)
        if n_rest:
            ci = rest[:n_rest]
            t[ci], prim[ci] = self._cast_idx(o, R32, x, y, ci)
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
        from mst.pipeline import render_kernels as rk

        H, W = cam.height, cam.width
        x, y, inv_norm = self.camera_dirs(cam)
        T = np.asarray(T_cam_model, np.float64)
        R_model_cam = T[:3, :3].T
        o = -mv(R_model_cam, T[:3, 3]) - self.origin
        R32 = R_model_cam.astype(np.float32)
        if full_cast or H < 4 or W < 4:
            t, prim = self._cast_idx(o, R32, x, y, np.zeros(0, np.int64))
        else:
            t, prim = self.primary_hits(cam, o, R_model_cam)
        focal = 0.5 * (cam.fx + cam.fy)
        tables = self._frame_tables(o)
        rgb = self.shade(R_model_cam, x, y, t, prim, focal, tables, inv_norm=inv_norm)
        edges = np.zeros((H, W), bool)
        if aa_samples:
            edges = self.edge_mask(prim, t, (H, W))
            e_idx = np.flatnonzero(edges)
            if len(e_idx):
                pat = aa_pattern(aa_samples)
                if cam.has_distortion:
                    uv = np.stack([e_idx % W, e_idx // W], axis=1).astype(np.float64)
                    xy = cam.unproject((uv[:, None, :] + pat[None, :, :]).reshape(-1, 2))
                    sx, sy = xy[:, 0].astype(np.float32), xy[:, 1].astype(np.float32)
                else:
                    sx = np.empty(len(e_idx) * len(pat), np.float32)
                    sy = np.empty(len(e_idx) * len(pat), np.float32)
                    rk.subpixel_dirs(e_idx, W, pat, cam.fx, cam.fy, cam.cx, cam.cy, sx, sy)
                t2, p2 = self._cast_idx(o, R32, sx, sy, np.zeros(0, np.int64))
                rgb[e_idx] = self.shade(R_model_cam, sx, sy, t2, p2, focal, tables, group=len(pat))
        depth = np.empty(H * W, np.float32)
        ids = np.empty(H * W, np.int64)
        rk.depth_ids(t, prim, len(self.F), depth, ids)
        out = {
            "rgb": rgb.reshape(H, W, 3),
            "depth": depth.reshape(H, W),
            "ids": ids.reshape(H, W),
            "edges": edges,
            "n_edge_px": int(edges.sum()),
        }
        if with_cos:
            hit = ids >= 0
            pc = np.where(hit, ids, 0)
            d = _rot(R_model_cam, x, y, 1.0)
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
