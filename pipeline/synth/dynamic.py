"""``mst synth turntable|carried|leave|occluder|blackout``: sequences where the world is not static or the view fails.

Unlike :mod:`mst.pipeline.synth` (a static scene, a moving camera), the object here moves in the
world or the view is interrupted, with ground truth for the object pose in the camera:

* ``turntable``: the camera stands still (a slight hand shake); the object rests, turns on a
  turntable (90 deg in a quarter of the frames), then rests again, on a textured floor in front of
  a textured wall. The map of a SLAM aid is made of the still room: only the model tells the
  object's motion (the static-world check of ``mst track``).
* ``carried``: the camera stands still (the turntable's shake); the object is carried along an
  arc across the floor (sideways by 0.15 of the view and along the line of sight, turning 20 deg) and
  put down again, while the room stays: as on the turntable, only the model tells the motion.
* ``leave``: the camera stands still; the object slides out of the view, is turned by 30 deg and
  moved while unseen, and slides back in to rest at another place (re-acquisition after loss).
* ``occluder``: a slow orbit; a dark, hand-sized slab sweeps between the camera and the object.
* ``blackout``: a slow orbit with 5 black frames (lens covered) and then a burst of 6 motion-blurred
  frames (fast shake, 8 sub-frame renders averaged).

The object has per-face shading plus a random checker texture fixed on its surface (a turned 3D
grid: keypoints and no symmetry), the room a smooth procedural texture. Outputs (the layout of
:mod:`mst.pipeline.synth`): ``rgb/%06d.png``, ``camera.json``, ``gt.txt`` (TUM: camera pose in the
model frame, t = frame / fps), ``cMo/%06d.txt``, ``clicks.txt`` (frame 0: ``X Y Z u v``),
``model.obj``, ``frames.csv`` (frame, object_moving, occluded_fraction, black, blur, in_view: the
truth a test needs, e.g. "fully visible and at rest"; in_view is the share of the model's bounding
box corners in front of the camera and inside the image) and ``scene.json`` (the parameters).

Frames: ``T_cam_model`` (model -> camera), the world z up with the floor at the model's lowest
point. Metres, pixels, degrees. CPU ray casting (:class:`mst.pipeline.render.Renderer`).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np

from mst.core.camera import Camera
from mst.core.poses import inv_T, look_at, make_T, transform_points

DYNAMIC_SCENARIOS = ("turntable", "carried", "leave", "occluder", "blackout")
DEFAULT_FRAMES_DYNAMIC = {"turntable": 80, "carried": 80, "leave": 90, "occluder": 60, "blackout": 60}
STILL_CAMERA = ("turntable", "carried", "leave")  #: the camera stands still, the object moves


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _box(lo, hi) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box triangles (outward)."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    V = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], float)
    F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
    return V, F


class DynamicScene:
    """Object, room and (optional) occluder with their per-frame poses; renders gray frames."""

    def __init__(self, scenario: str, V: np.ndarray, F: np.ndarray, cfg, cam: Camera):
        from mst.pipeline.render import Renderer

        if scenario not in DYNAMIC_SCENARIOS:
            raise ValueError(scenario)
        self.scenario, self.cfg, self.cam = scenario, cfg, cam
        self.n = int(cfg.frames if cfg.frames is not None else DEFAULT_FRAMES_DYNAMIC[scenario])
        lo, hi = V.min(0), V.max(0)
        self.obj_lo_hi = (lo, hi)
        self.size = float(np.ptp(V, axis=0).max())
        self.c_model = 0.5 * (lo + hi)
        # world: object centre above the origin, floor at the model's lowest point
        self.T_world_model0 = make_T(np.eye(3), -np.array([self.c_model[0], self.c_model[1], lo[2]]))
        self.obj = Renderer(V, F)
        self.n_obj = len(F)
        fov_v = 2 * math.atan(0.5 * cam.height / cam.fy)
        r = 0.5 * float(np.linalg.norm(hi - lo))
        self.D = float(cfg.distance or r / math.sin(0.35 * fov_v))
        R = 3.0 * self.D
        Vf = np.array([[-R, -R, 0], [R, -R, 0], [R, R, 0], [-R, R, 0]], float) - [0, 0, 1e-3 * self.size]
        Vw = np.array([[-R, 0.6 * R, 0], [R, 0.6 * R, 0], [R, 0.6 * R, R], [-R, 0.6 * R, R]], float)
        self.room = Renderer(np.r_[Vf, Vw], np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]]))
        s = self.size
        Vo, Fo = _box([-0.12 * s, -0.35 * s, -0.05 * s], [0.12 * s, 0.35 * s, 0.05 * s])  # camera frame: upright slab
        self.occ = Renderer(Vo, Fo) if scenario == "occluder" else None
        rng = np.random.default_rng([int(cfg.seed), 11])
        light = np.array([0.4, -0.5, 0.75]) / np.linalg.norm([0.4, -0.5, 0.75])
        self.face_col = 70 + 110 * (0.5 + 0.5 * np.abs(self.obj.normals @ light))
        self.lut = rng.uniform(-25.0, 25.0, 4096)
        self.shift = rng.random(3)
        self.Rg = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        d = rng.normal(size=(10, 3))
        self.freq = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(2.0, 9.0, (10, 1)) / self.size
        self.phase = rng.uniform(0, 2 * np.pi, 10)
        self.rng = np.random.default_rng([int(cfg.seed), 12])

    # ------------------------------------------------------------------ truth per frame
    def moving_span(self) -> tuple[int, int]:
        """First and last frame of the object's motion (the whole excursion for ``leave``)."""
        if self.scenario == "leave":
            return int(0.25 * self.n), int(0.7 * self.n)
        if self.scenario == "carried":
            return int(0.3 * self.n), int(0.6 * self.n)
        return int(0.3 * self.n), int(0.55 * self.n)

    def _right(self) -> np.ndarray:
        """The camera's right direction on the floor (world, unit) at frame 0."""
        r = inv_T(self.T_cam_world(0.0))[:3, 0].copy()
        r[2] = 0.0
        return r / np.linalg.norm(r)

    def T_world_model(self, k: float) -> np.ndarray:
        if self.scenario not in STILL_CAMERA:
            return self.T_world_model0
        a0, a1 = self.moving_span()

        def ease(k0, k1):  # 0 -> 1 over [k0, k1], smooth start and stop
            u = float(np.clip((k - k0) / max(k1 - k0, 1), 0.0, 1.0))
            return 0.5 - 0.5 * math.cos(math.pi * u)

        if self.scenario == "turntable":
            return make_T(_rot_z(math.radians(90.0) * ease(a0, a1)), np.zeros(3)) @ self.T_world_model0
        right = self._right()
        fwd = np.cross([0.0, 0.0, 1.0], right)  # away from the camera on the floor
        fov_h = 2 * math.atan(0.5 * self.cam.width / self.cam.fx)
        half_w = self.D * math.tan(0.5 * fov_h)  # half the view's width at the object (m)
        if self.scenario == "carried":  # an arc: sideways by 0.15 of the view and along the line of sight, turning 20 deg
            u = ease(a0, a1)
            t = -right * 0.3 * half_w * u + fwd * 0.2 * self.D * math.sin(math.pi * u)
            return make_T(_rot_z(math.radians(20.0) * u), t) @ self.T_world_model0
        # leave: out to the right (beyond the image border by the object's size), turned and moved
        # while unseen, back in to rest a quarter of the view left of the start
        out = half_w + 1.5 * self.size
        m = a0 + (a1 - a0) / 3.0
        b = a0 + 2.0 * (a1 - a0) / 3.0
        u_out, u_turn, u_in = ease(a0, m), ease(m, b), ease(b, a1)
        x = out * u_out * (1.0 - u_in) - 0.25 * half_w * u_in
        t = right * x + fwd * 0.1 * self.D * u_turn
        return make_T(_rot_z(math.radians(30.0) * u_turn), t) @ self.T_world_model0

    def T_cam_world(self, k: float) -> np.ndarray:
        el = math.radians(25.0)
        if self.scenario in STILL_CAMERA:
            az = math.radians(-70.0) + 0.002 * math.sin(0.9 * k)
        else:
            az = math.radians(-70.0 + 0.5 * k)
        eye = self.D * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        target = np.array([0.0, 0.0, 0.5 * (self.c_model[2] - 0.0)]) + [0, 0, 0.3 * self.size]
        if self.scenario == "blackout" and self.is_blur(int(k)):
            target = target + 0.02 * self.D * np.array([math.sin(7.0 * k), math.cos(5.0 * k), 0.0])
        return inv_T(look_at(eye, target))

    def T_world_occ(self, k: int) -> np.ndarray | None:
        if self.occ is None:
            return None
        a0, a1 = int(0.3 * self.n), int(0.6 * self.n)
        u = (k - a0) / max(a1 - a0, 1)
        if not 0.0 <= u <= 1.0:
            return None
        # between camera and object, sweeping across the view
        Tcw = self.T_cam_world(k)
        Xc = np.array([(-1.0 + 2.0 * u) * 0.8 * self.size, 0.0, 0.45 * self.D])
        return inv_T(Tcw) @ make_T(np.eye(3), Xc)

    def is_black(self, k: int) -> bool:
        return self.scenario == "blackout" and int(0.3 * self.n) <= k < int(0.3 * self.n) + 5

    def is_blur(self, k: int) -> bool:
        return self.scenario == "blackout" and int(0.6 * self.n) <= k < int(0.6 * self.n) + 6

    def in_view(self, k: int) -> float:
        """Share of the model's 8 bounding-box corners in front of the camera and inside the image."""
        lo, hi = self.obj_lo_hi
        C = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        Xc = transform_points(self.T_cam_model(k), C)
        front = Xc[:, 2] > 0
        uv = self.cam.project(np.where(front[:, None], Xc, 1.0))
        ok = front & (uv[:, 0] >= 0) & (uv[:, 0] <= self.cam.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= self.cam.height - 1)
        return float(ok.mean())

    def T_cam_model(self, k: float) -> np.ndarray:
        return self.T_cam_world(k) @ self.T_world_model(k)

    # ------------------------------------------------------------------ rendering
    def _render_once(self, k: float) -> tuple[np.ndarray, float]:
        cam = self.cam
        Tcm = self.T_cam_model(k)
        Tcw = self.T_cam_world(k)
        z_o, id_o = self.obj.render_depth_ids(cam, Tcm)
        z_r, id_r = self.room.render_depth_ids(cam, Tcw)
        zo = np.where(id_o >= 0, z_o, np.inf)
        zr = np.where(id_r >= 0, z_r, np.inf)
        H, W = zo.shape
        vv, uu = np.mgrid[0:H, 0:W]
        K = cam.K
        img = np.full((H, W), 190.0, np.float32)
        room = np.isfinite(zr) & (zr <= zo)
        X = self._backproject(uu[room], vv[room], zr[room], K, Tcw)
        # float32 phases (10x faster sine at 640x480; the gray levels change by < 1e-4)
        ph = X.astype(np.float32) @ self.freq.T.astype(np.float32) + self.phase.astype(np.float32)
        img[room] = 128 + 70 * np.tanh(0.7 * np.sin(ph).sum(1))
        obj = np.isfinite(zo) & (zo < zr)
        Xm = self._backproject(uu[obj], vv[obj], zo[obj], K, Tcm)
        q = np.floor(Xm @ self.Rg.T / (0.07 * self.size) + self.shift).astype(np.int64)
        h = (q[:, 0] * 73856093) ^ (q[:, 1] * 19349663) ^ (q[:, 2] * 83492791)
        img[obj] = self.face_col[id_o[obj]] + self.lut[h % 4096]
        occ_frac = 0.0
        Two = self.T_world_occ(int(k)) if self.occ is not None else None
        if Two is not None:
            z_c, id_c = self.occ.render_depth_ids(cam, Tcw @ Two)
            zc = np.where(id_c >= 0, z_c, np.inf)
            front = np.isfinite(zc) & (zc < np.minimum(zo, zr))
            img[front] = 45.0 + 8.0 * np.sin(0.3 * uu[front]) * np.cos(0.2 * vv[front])
            n_obj = int(obj.sum())
            occ_frac = float((obj & front).sum() / n_obj) if n_obj else 0.0
        return img, occ_frac

    @staticmethod
    def _backproject(u, v, z, K, T_cam_x) -> np.ndarray:
        # X = R^T (Xc - t), column by column (a (N,3) @ (3,3) product is several times slower)
        x, y = (u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z
        R, t = T_cam_x[:3, :3], T_cam_x[:3, 3]
        c = -R.T @ t
        return np.stack([R[0, j] * x + R[1, j] * y + R[2, j] * z + c[j] for j in range(3)], 1)

    def render(self, k: int) -> tuple[np.ndarray, float]:
        """(H, W) uint8 gray frame k and the share of the object's pixels hidden by the occluder."""
        if self.is_black(k):
            img, occ = np.zeros((self.cam.height, self.cam.width), np.float32), 1.0
        elif self.is_blur(k):
            subs = [self._render_once(k + (j - 3.5) / 8.0 * 0.9)[0] for j in range(8)]
            img, occ = np.mean(subs, 0), 0.0
        else:
            img, occ = self._render_once(k)
        img = img + self.rng.normal(0, float(self.cfg.rgb_noise), img.shape).astype(np.float32)
        return np.clip(img, 0, 255).astype(np.uint8), occ


def synthesize_dynamic(scenario: str, model_path: str | os.PathLike, out_dir: str | os.PathLike, cfg,
                       progress=None, overwrite: bool = False) -> dict:
    """Render ``scenario`` (:data:`DYNAMIC_SCENARIOS`) of ``model_path`` into ``out_dir`` (module doc).

    ``cfg``: a :class:`mst.pipeline.synth.SynthConfig` (frames, fps, width, height, focal_px,
    distance, seed, rgb_noise are used). Returns the summary dict of :func:`mst.pipeline.synth.synthesize`.
    """
    import time

    import cv2

    from mst.core.camera import write_camera
    from mst.core.trajectory import format_tum, write_pose_file
    from mst.meshtools.formats import save_triangles
    from mst.pipeline.synth.scene import load_model_triangles, model_corners
    from mst.pipeline.synth.writers import _commit_out_dir, _prepare_out_dir

    t0 = time.perf_counter()
    model_path = Path(model_path)
    V, F = load_model_triangles(model_path)
    f = float(cfg.focal_px or 525.0 * cfg.width / 640.0)
    cam = Camera(f, f, (cfg.width - 1) / 2.0, (cfg.height - 1) / 2.0, cfg.width, cfg.height)
    sc = DynamicScene(scenario, V, F, cfg, cam)
    tmp = _prepare_out_dir(Path(out_dir), overwrite)
    render_s = 0.0
    try:
        (tmp / "rgb").mkdir()
        (tmp / "cMo").mkdir()
        rows, T_mc = [], []
        a0, a1 = sc.moving_span()
        for k in range(sc.n):
            tr = time.perf_counter()
            img, occ = sc.render(k)
            render_s += time.perf_counter() - tr
            cv2.imwrite(str(tmp / "rgb" / f"{k:06d}.png"), img)
            T = sc.T_cam_model(k)
            write_pose_file(tmp / "cMo" / f"{k:06d}.txt", T, k / cfg.fps)
            T_mc.append(inv_T(T))
            moving = scenario in STILL_CAMERA and a0 <= k <= a1
            rows.append(f"{k},{int(moving)},{occ:.4f},{int(sc.is_black(k))},{int(sc.is_blur(k))},{sc.in_view(k):.3f}")
            if progress is not None:
                progress(1)
        (tmp / "gt.txt").write_text(format_tum(np.arange(sc.n) / cfg.fps, np.array(T_mc)))
        (tmp / "frames.csv").write_text("frame,object_moving,occluded_fraction,black,blur,in_view\n" + "\n".join(rows) + "\n")
        write_camera(tmp / "camera.json", cam)
        save_triangles(tmp / "model.obj", V, F)
        corners = V[model_corners(V, F)]
        T0 = sc.T_cam_model(0)
        Xc = transform_points(T0, corners)
        uv = cam.project(Xc)
        inside = (Xc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        clk = [f"{x:.6f} {y:.6f} {z:.6f} {u:.3f} {v:.3f}" for (x, y, z), (u, v) in zip(corners[inside], uv[inside])][:8]
        (tmp / "clicks.txt").write_text("\n".join(clk) + "\n")
        params = {"scenario": scenario, "frames": sc.n, "fps": cfg.fps, "width": cfg.width, "height": cfg.height,
                  "focal_px": f, "distance": sc.D, "seed": cfg.seed, "moving_frames": [a0, a1] if scenario in STILL_CAMERA else None,
                  "model": str(model_path)}
        (tmp / "scene.json").write_text(json.dumps({"dynamic": params}, indent=2) + "\n")
    except BaseException:
        import shutil

        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _commit_out_dir(tmp, Path(out_dir))
    return {"frames": sc.n, "scenario": scenario, "width": cfg.width, "height": cfg.height, "distance_m": sc.D,
            "out_dir": str(out_dir), "render_ms_per_frame": 1e3 * render_s / max(sc.n, 1), "clicks": len(clk),
            "total_s": time.perf_counter() - t0, "config": cfg.to_dict()}
