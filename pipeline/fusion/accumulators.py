"""Streaming accumulators of the fusion: a sorted voxel grid, a plain point list and Open3D's TSDF.

Memory grows with the output (occupied voxels or kept points), never with the sequence length.
"""

from __future__ import annotations

import numpy as np

from mst.errors import ConfigError


class VoxelAccumulator:
    """Streaming voxel-grid average: memory grows with the number of occupied voxels only.

    Points are given relative to a fixed local origin (metres). Voxel keys pack the three integer
    voxel coordinates (21 bits each, +-1,048,575 voxels, i.e. +-10 km at 1 cm) into one int64;
    the state is kept sorted by key so each frame merges with ``np.searchsorted`` (no Python loop
    per point or per voxel).
    """

    BITS = 21
    OFF = 1 << (BITS - 1)

    def __init__(self, voxel: float):
        self.voxel = float(voxel)
        self.keys = np.empty(0, np.int64)
        self.sum = np.empty((0, 3))
        self.count = np.empty(0, np.int64)
        self.csum = np.empty((0, 3))
        self.ccount = np.empty(0, np.int64)

    def __len__(self) -> int:
        return len(self.keys)

    def pack(self, X_local: np.ndarray) -> np.ndarray:
        ijk = np.floor(X_local / self.voxel).astype(np.int64)
        if len(ijk) and (np.abs(ijk).max() >= self.OFF):
            raise ConfigError("voxel_m", f"{self.voxel:g} m is too small: the points span more than "
                                         f"{self.OFF * self.voxel:g} m from the first camera")
        ijk += self.OFF
        return (ijk[:, 0] << (2 * self.BITS)) | (ijk[:, 1] << self.BITS) | ijk[:, 2]

    def add(self, X_local: np.ndarray, rgb: np.ndarray | None = None, rgb_ok: np.ndarray | None = None) -> None:
        """Add (N, 3) float64 local points, optional (N, 3) uint8 colours with a validity mask."""
        if len(X_local) == 0:
            return
        key = self.pack(X_local)
        uk, inv = np.unique(key, return_inverse=True)
        m = len(uk)
        s = np.stack([np.bincount(inv, weights=X_local[:, i], minlength=m) for i in range(3)], axis=1)
        c = np.bincount(inv, minlength=m).astype(np.int64)
        if rgb is not None:
            okw = rgb_ok.astype(np.float64)
            cs = np.stack([np.bincount(inv, weights=rgb[:, i] * okw, minlength=m) for i in range(3)], axis=1)
            cc = np.bincount(inv, weights=okw, minlength=m).astype(np.int64)
        else:
            cs, cc = np.zeros((m, 3)), np.zeros(m, np.int64)
        pos = np.searchsorted(self.keys, uk)
        found = pos < len(self.keys)
        found[found] = self.keys[pos[found]] == uk[found]
        p = pos[found]
        self.sum[p] += s[found]
        self.count[p] += c[found]
        self.csum[p] += cs[found]
        self.ccount[p] += cc[found]
        new = ~found
        if new.any():
            at = pos[new]
            self.keys = np.insert(self.keys, at, uk[new])
            self.sum = np.insert(self.sum, at, s[new], axis=0)
            self.count = np.insert(self.count, at, c[new])
            self.csum = np.insert(self.csum, at, cs[new], axis=0)
            self.ccount = np.insert(self.ccount, at, cc[new])

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(X_local (M, 3) centroids, rgb (M, 3) uint8 (0 where never coloured), count (M,))``."""
        X = self.sum / self.count[:, None]
        rgb = np.rint(self.csum / np.maximum(self.ccount, 1)[:, None]).clip(0, 255).astype(np.uint8)
        return X, rgb, self.count


class PointList:
    """``voxel = 0``: keep every sample (memory = the output cloud)."""

    def __init__(self) -> None:
        self.X: list[np.ndarray] = []
        self.rgb: list[np.ndarray] = []

    def __len__(self) -> int:
        return sum(len(x) for x in self.X)

    def add(self, X_local: np.ndarray, rgb: np.ndarray | None = None, rgb_ok: np.ndarray | None = None) -> None:
        self.X.append(X_local)
        self.rgb.append(rgb if rgb is not None else np.zeros((len(X_local), 3), np.uint8))

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        X = np.concatenate(self.X) if self.X else np.empty((0, 3))
        rgb = np.concatenate(self.rgb) if self.rgb else np.empty((0, 3), np.uint8)
        return X, rgb, np.ones(len(X), np.int64)


class TSDFAccumulator:
    """Open3D ``t.geometry.VoxelBlockGrid`` TSDF on the CPU (``ScalableTSDFVolume`` is broken in 0.20).

    Integrates filtered depth (metres) in the local frame; :meth:`result` extracts the surface
    points (voxels with weight > ``weight_threshold``; Open3D's test is strict).
    """

    def __init__(self, voxel: float, trunc_voxels: float, depth_max: float, weight_threshold: float, with_color: bool):
        import open3d as o3d
        import open3d.core as o3c

        self.o3d, self.o3c = o3d, o3c
        self.dev = o3c.Device("CPU:0")
        self.with_color = with_color
        names = ("tsdf", "weight", "color") if with_color else ("tsdf", "weight")
        self.vbg = o3d.t.geometry.VoxelBlockGrid(names, (o3c.float32,) * len(names), tuple([1, 1, 3][: len(names)]),
                                                 float(voxel), 16, 1000, self.dev)
        self.trunc_voxels = float(trunc_voxels)  # Open3D's trunc_voxel_multiplier (voxels, not metres)
        self.depth_max = float(depth_max)
        self.weight_threshold = float(weight_threshold)

    def __len__(self) -> int:
        return int(self.vbg.hashmap().size())

    def integrate(self, depth_m: np.ndarray, K: np.ndarray, T_cam_local: np.ndarray, rgb_img: np.ndarray | None) -> None:
        o3d, o3c = self.o3d, self.o3c
        di = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth_m, np.float32)))
        # Open3D's pixel (u, v) spans [u, u + 1) (its rays go through u + 0.5); mst's pixel (0, 0) is
        # the centre of the top-left pixel, so the principal point moves by half a pixel (measured:
        # median distance to the surface 7 mm without the shift, 0.1 mm with it, at 3 m / f = 140 px)
        K_o3d = np.array(K, dtype=np.float64)
        K_o3d[:2, 2] += 0.5
        Kt = o3c.Tensor(K_o3d)
        Et = o3c.Tensor(np.ascontiguousarray(T_cam_local, np.float64))
        coords = self.vbg.compute_unique_block_coordinates(di, Kt, Et, 1.0, self.depth_max, self.trunc_voxels)
        if self.with_color:
            ci = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(rgb_img, np.float32)))
            self.vbg.integrate(coords, di, ci, Kt, Et, 1.0, self.depth_max, self.trunc_voxels)
        else:
            self.vbg.integrate(coords, di, Kt, Et, 1.0, self.depth_max, self.trunc_voxels)

    def result(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if len(self) == 0:
            return np.empty((0, 3)), np.empty((0, 3), np.uint8), np.empty(0, np.int64)
        pcd = self.vbg.extract_point_cloud(weight_threshold=self.weight_threshold)
        if "positions" not in pcd.point or pcd.point.positions.shape[0] == 0:
            return np.empty((0, 3)), np.empty((0, 3), np.uint8), np.empty(0, np.int64)
        X = pcd.point.positions.numpy().astype(np.float64)
        if self.with_color and "colors" in pcd.point:
            rgb = np.rint(pcd.point.colors.numpy() * 255).clip(0, 255).astype(np.uint8)
        else:
            rgb = np.zeros((len(X), 3), np.uint8)
        return X, rgb, np.ones(len(X), np.int64)
