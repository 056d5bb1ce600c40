"""``mst synth``: synthetic colour / depth sequences of a model in a textured environment, with ground truth.

Stage function: :func:`synthesize` ``(scenario, model_path, out_dir, config) -> summary dict``.

Frames and units: everything (model, environment, camera poses) is expressed in the *model frame*,
in metres. Scenarios are designed in a *canonical frame* whose +z is the model's up axis
(``config.up``, default ``z``); ``R_model_canon`` maps it back. The camera frame is x right, y down,
z forward; ``T_cam_model`` is ViSP's cMo; TUM files hold ``T_model_cam``.

Output folder (the layout the other stages read)::

    rgb/000000.png ...     8-bit colour (PNG), Lambertian shading, sensor noise
    depth/000000.png       uint16 millimetres, 0 = no depth       (with config.depth)
    depth/000000.npy       float32 metres, 0 = no depth
    video.mp4              the colour frames (mp4v)                 (with config.video)
    camera.json            intrinsics (mst camera file)
    gt.txt                 TUM: t = frame / fps, camera pose in the model frame
    cMo/000000.txt         4x4 model-to-camera matrix per frame (row-major)
    clicks.txt             frame-0 clicks "X Y Z u v": visible model corners and their pixels
    model.obj              the object's triangles as rendered (full float64 precision)
    scene.ply              model + environment as one mesh (face property ``label``: 0 model,
                           1 floor/ground, 2 walls, 3 ceiling)
    scene.json             scenario, seed, all parameters: ``mst synth --from-scene`` reproduces
    frames.csv             per frame: t, model pixels, supersampled edge pixels

Scenarios: ``orbit`` (the camera circles the model, always looking at it, with height and roll
variation), ``corridor`` (walking past the model along a textured corridor; the camera turns away so
that the model leaves the view for the middle ~40% of the sequence and comes back), ``flyover``
(a UAV-like straight pass at ``distance`` metres above the model top, default clamp(0.3 x model
diagonal, 30, 150) m, at max(8, distance/4) m/s, looking at the model, pitched toward its facades),
``fast`` (any ``base`` scenario with only every ``drop``-th frame kept).

Colour noise (``rgb_noise`` sigma, 8-bit levels): per pixel and channel, the standardised sum of four
uniform random bytes (near-Gaussian, tails cut at 3.45 sigma), added before rounding to 8 bits.

Depth noise model (``depth_noise="kinect"``): axial noise sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m
(Nguyen, Izadi & Lovell 2012, Kinect v1), then disparity quantisation to 1/8 pixel with a 7.5 cm
baseline, holes at depth discontinuities (jump > 5% of z, grown by one pixel), at grazing angles
(> 80 deg from the normal), closer than 0.3 m, and 0.2% random dropouts. ``depth_noise="none"``
writes the exact z-depth of each pixel centre.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import numpy as np

from mst import InputError, MstError, __version__
from mst.core.camera import Camera, write_camera
from mst.core.poses import inv_T, look_at, make_T  # noqa: F401  (look_at re-exported)
from mst.core.trajectory import format_tum
from mst.pipeline.render import row_ids

SCENARIOS = ("orbit", "corridor", "flyover", "fast", "turntable", "occluder", "blackout")  # the last 3: synth_dynamic
BASE_SCENARIOS = ("orbit", "corridor", "flyover")
DEFAULT_FRAMES = {"orbit": 120, "corridor": 150, "flyover": 120, "fast": 60, "turntable": 80, "occluder": 60, "blackout": 60}
UP_AXES = {"z": (0, 0, 1), "-z": (0, 0, -1), "y": (0, 1, 0), "-y": (0, -1, 0), "x": (1, 0, 0), "-x": (-1, 0, 0)}

# material ids (also the ``label`` face property of scene.ply)
MODEL, FLOOR, WALL, CEILING = 0, 1, 2, 3


@dataclass
class SynthConfig:
    """Parameters of :func:`synthesize` (``None`` = scenario default, resolved into scene.json).

    Units: metres, seconds, pixels, degrees.
    """

    frames: int | None = None          # output frames (default: orbit 120, corridor 150, flyover 120, fast 60)
    fps: float = 30.0                  # frame rate; gt.txt time = frame index / fps
    width: int = 640
    height: int = 480
    focal_px: float | None = None      # fx = fy (default 525 * width / 640)
    speed: float | None = None         # camera speed, m/s (default: scenario pace, see _resolve)
    distance: float | None = None      # camera-to-model distance (orbit/corridor) or height above it (flyover), m
    seed: int = 0
    drop: int | None = None            # keep every drop-th frame of the base trajectory (fast: 8)
    base: str = "orbit"                # base scenario of "fast"
    depth: bool = True                 # write depth/
    depth_noise: str = "none"          # "none" | "kinect"
    rgb_noise: float = 2.0             # colour noise sigma, 8-bit levels (near-Gaussian: sum of 4 uniforms)
    motion_blur: int = 1               # sub-frame renders averaged per frame (1 = none)
    shutter: float = 0.5               # exposure as a fraction of the frame interval (motion blur)
    model_texture: bool = False        # texture the model too (default: flat, per-face shading)
    floor: str = "concrete"            # orbit/corridor floor texture: "concrete" | "tiles" (flyover: terrain)
    environment: bool = True           # ground/walls around the model
    click_noise: float = 0.0           # Gaussian noise (pixels) added to the clicks' u, v
    n_clicks: int = 6                  # clicked corners (at least 4)
    up: str = "z"                      # the model's up axis
    video: bool = False                # also write video.mp4
    aa_samples: int = 16               # sub-pixel rays per silhouette/crease pixel (0, 4, 8, 16)
    texture_size: int = 2048           # texels per texture tile side (power of two)
    nthreads: int = 0                  # ray-casting threads (0 = all cores)

    @classmethod
    def from_dict(cls, d: dict) -> SynthConfig:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown synth parameters: {sorted(unknown)}")
        return cls(**d)


# ---------------------------------------------------------------------------- geometry helpers
def R_canon_from_up(up: str) -> np.ndarray:
    """Rotation ``R_canon_model`` taking the model's ``up`` axis to canonical +z (a proper rotation)."""
    if up not in UP_AXES:
        raise ValueError(f"unknown up axis {up!r} (expected one of {', '.join(UP_AXES)})")
    u = np.array(UP_AXES[up], np.float64)
    z = np.array([0.0, 0.0, 1.0])
    if np.allclose(u, z):
        return np.eye(3)
    if np.allclose(u, -z):
        return np.diag([1.0, -1.0, -1.0])
    axis = np.cross(u, z)
    axis /= np.linalg.norm(axis)
    # rotation by 90 degrees about axis (u and z are orthogonal here)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + K + K @ K


def _quad(p0, p1, p2, p3) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles of the quad p0 p1 p2 p3 (counter-clockwise seen from the side its normal points to)."""
    return np.array([p0, p1, p2, p3], np.float64), np.array([[0, 1, 2], [0, 2, 3]])


def _box_room(lo: np.ndarray, hi: np.ndarray, floor: bool, walls: bool, ceiling: bool):
    """Inward-facing room ``[lo, hi]`` (canonical frame): list of (V, F, material) quads."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    q = []
    if floor:
        q.append((*_quad((x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0)), FLOOR))
    if ceiling:
        q.append((*_quad((x0, y0, z1), (x0, y1, z1), (x1, y1, z1), (x1, y0, z1)), CEILING))
    if walls:
        q.append((*_quad((x0, y0, z0), (x0, y0, z1), (x1, y0, z1), (x1, y0, z0)), WALL))  # y = y0, facing +y
        q.append((*_quad((x0, y1, z0), (x1, y1, z0), (x1, y1, z1), (x0, y1, z1)), WALL))  # y = y1, facing -y
        q.append((*_quad((x0, y0, z0), (x0, y1, z0), (x0, y1, z1), (x0, y0, z1)), WALL))  # x = x0, facing +x
        q.append((*_quad((x1, y0, z0), (x1, y0, z1), (x1, y1, z1), (x1, y1, z0)), WALL))  # x = x1, facing -x
    return q


def _smoothstep(a: float, b: float, x: float) -> float:
    s = min(max((x - a) / (b - a), 0.0), 1.0)
    return s * s * (3 - 2 * s)


# ---------------------------------------------------------------------------- scenarios
@dataclass
class Scene:
    """A resolved scenario in the canonical frame (z up): model bounds, environment, trajectory parameters."""

    scenario: str
    params: dict                      # resolved numbers (JSON-able), stored in scene.json
    env: list = field(default_factory=list)   # [(V (4,3), F (2,3), material)]

    def pose(self, s: float) -> np.ndarray:
        """Camera pose ``T_canon_cam`` at base-trajectory time ``s`` (seconds)."""
        p = self.params
        c = np.array(p["center"])
        if self.scenario == "orbit":
            D = p["distance"]
            el = math.radians(p["elevation_deg"] + p["elevation_amp_deg"] * math.sin(2 * math.pi * s / 6.0))
            az = math.radians(p["azimuth0_deg"]) + p["speed"] * s / (D * math.cos(math.radians(p["elevation_deg"])))
            eye = c + D * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
            wob = p["wobble"] * np.array([math.sin(1.3 * s), math.cos(0.9 * s), 0.5 * math.sin(0.7 * s)])
            return look_at(eye, c + wob, roll_deg=3.0 * math.sin(2 * math.pi * s / 5.0))
        if self.scenario == "corridor":
            T = p["duration"]
            x = p["x_start"] + p["speed"] * s
            eye = np.array([x, p["eye_y"], p["eye_z"] + 0.02 * p["distance"] * math.sin(2 * math.pi * s * 1.8)])
            u = s / T if T > 0 else 0.0
            w = _smoothstep(0.18, 0.30, u) - _smoothstep(0.62, 0.80, u)  # 1 = looking away from the model
            to_model = c - eye
            yaw_m = math.atan2(to_model[1], to_model[0])
            pitch_m = math.atan2(to_model[2], math.hypot(to_model[0], to_model[1]))
            yaw_a = math.radians(p["away_yaw_deg"])
            dyaw = (yaw_a - yaw_m + math.pi) % (2 * math.pi) - math.pi
            yaw = yaw_m + w * dyaw
            pitch = (1 - w) * pitch_m + w * math.radians(-6.0)
            fwd = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
            return look_at(eye, eye + fwd, roll_deg=1.5 * math.sin(2 * math.pi * s / 2.3))
        if self.scenario == "flyover":
            x = p["x_start"] + p["speed"] * s
            eye = np.array([x, p["eye_y"], p["eye_z"] + 0.01 * p["distance"] * math.sin(2 * math.pi * s / 4.0)])
            target = c + np.array([0.3 * (x - c[0]), 0.0, -0.25 * p["model_height"]])
            return look_at(eye, target, roll_deg=2.0 * math.sin(2 * math.pi * s / 7.0))
        raise ValueError(self.scenario)


def focus_point(Vc: np.ndarray, F: np.ndarray) -> np.ndarray:
    """A point on the model to fly toward: the centroid of the triangle nearest the area-weighted
    centroid (sparse city models can have an empty bounding-box centre). Canonical frame."""
    C = Vc[F].mean(axis=1)
    area = 0.5 * np.linalg.norm(np.cross(Vc[F[:, 1]] - Vc[F[:, 0]], Vc[F[:, 2]] - Vc[F[:, 0]]), axis=1)
    g = (C * area[:, None]).sum(0) / max(area.sum(), 1e-12)
    return C[int(np.argmin(np.linalg.norm(C[:, :2] - g[:2], axis=1)))]


def _resolve(scenario: str, cfg: SynthConfig, lo: np.ndarray, hi: np.ndarray, cam: Camera,
             focus: np.ndarray | None = None) -> Scene:
    """Scenario geometry from the model's canonical bounding box ``[lo, hi]`` and the camera.

    ``focus``: the point a flyover looks at (default: the bounding-box centre)."""
    base = cfg.base if scenario == "fast" else scenario
    if base not in BASE_SCENARIOS:
        raise ValueError(f"unknown base scenario {base!r} (expected one of {', '.join(BASE_SCENARIOS)})")
    frames = int(cfg.frames if cfg.frames is not None else DEFAULT_FRAMES[scenario])
    drop = int(cfg.drop if cfg.drop is not None else (8 if scenario == "fast" else 1))
    n_base = (frames - 1) * drop + 1
    duration = (n_base - 1) / cfg.fps
    c = 0.5 * (lo + hi)
    ext = hi - lo
    diag = float(np.linalg.norm(ext)) or 1.0
    r_sphere = 0.5 * diag
    r_xy = 0.5 * float(np.linalg.norm(ext[:2]))
    fov_v = 2 * math.atan(0.5 * cam.height / cam.fy)
    d_fit = r_sphere / math.sin(0.35 * fov_v)  # the model's bounding sphere spans ~70% of the height
    p: dict = {"base": base, "frames": frames, "drop": drop, "base_frames": n_base, "duration": duration,
               "center": c.tolist(), "model_lo": lo.tolist(), "model_hi": hi.tolist(),
               "model_height": float(ext[2])}
    env: list = []
    if base == "orbit":
        D = float(cfg.distance or d_fit)
        el0 = 25.0
        speed = float(cfg.speed if cfg.speed is not None else 2 * math.pi * D * math.cos(math.radians(el0)) / 12.0)
        p.update(distance=D, elevation_deg=el0, elevation_amp_deg=8.0, azimuth0_deg=-60.0, speed=speed,
                 wobble=0.03 * r_sphere)
        R = 1.7 * D + r_xy
        wall_top = c[2] + 1.0 * D
        if cfg.environment:
            env = _box_room(np.array([c[0] - R, c[1] - R, lo[2]]), np.array([c[0] + R, c[1] + R, wall_top]),
                            True, True, False)
        p["room"] = [c[0] - R, c[1] - R, lo[2], c[0] + R, c[1] + R, wall_top]
        p["texture_distance"] = D
    elif base == "corridor":
        D = float(cfg.distance or d_fit)
        path = 2.2 * D
        speed = float(cfg.speed if cfg.speed is not None else (path / duration if duration > 0 else 0.0))
        length = speed * duration
        eye_y = c[1] - 0.5 * ext[1] - D
        eye_z = c[2] + 0.1 * diag
        x_start = c[0] - 0.5 * length
        p.update(distance=D, speed=speed, path_length=length, x_start=x_start, eye_y=eye_y, eye_z=eye_z,
                 away_yaw_deg=-40.0)
        y0 = eye_y - 0.8 * D
        y1 = hi[1] + 0.8 * D
        x0 = c[0] - 0.5 * length - 0.8 * D
        x1 = c[0] + 0.5 * length + 0.8 * D
        z1 = max(eye_z, hi[2]) + 0.6 * D
        if cfg.environment:
            env = _box_room(np.array([x0, y0, lo[2]]), np.array([x1, y1, z1]), True, True, True)
        p["room"] = [x0, y0, lo[2], x1, y1, z1]
        p["texture_distance"] = D
    else:  # flyover
        D = float(cfg.distance or min(max(30.0, 0.3 * diag), 150.0))
        off = 0.9 * D
        speed = float(cfg.speed if cfg.speed is not None else max(8.0, D / 4.0))  # UAV pace, m/s
        length = speed * duration
        fc = c if focus is None else np.array([focus[0], focus[1], c[2]])
        p["center"] = fc.tolist()
        p.update(distance=D, speed=speed, path_length=length, x_start=fc[0] - 0.5 * length,
                 eye_y=fc[1] - off, eye_z=hi[2] + D)
        G = 0.5 * length + 5 * D + r_xy
        if cfg.environment:
            env = _box_room(np.array([c[0] - G, c[1] - G, lo[2]]), np.array([c[0] + G, c[1] + G, lo[2] + 1.0]),
                            True, False, False)
        p["room"] = [c[0] - G, c[1] - G, lo[2], c[0] + G, c[1] + G, lo[2]]
        p["texture_distance"] = 1.4 * D
    return Scene(scenario=base, params=p, env=env)


# ---------------------------------------------------------------------------- mesh I/O
def write_ply_mesh(path: Path, V: np.ndarray, F: np.ndarray, labels: np.ndarray) -> None:
    """Binary little-endian PLY: double vertices, int triangles, uchar face ``label``."""
    V = np.asarray(V, "<f8")
    F = np.asarray(F, "<i4")
    head = ("ply\nformat binary_little_endian 1.0\ncomment mst synth scene: labels 0 model 1 floor 2 wall 3 ceiling\n"
            f"element vertex {len(V)}\nproperty double x\nproperty double y\nproperty double z\n"
            f"element face {len(F)}\nproperty list uchar int vertex_indices\nproperty uchar label\nend_header\n")
    rec = np.zeros(len(F), dtype=[("n", "u1"), ("i", "<i4", (3,)), ("label", "u1")])
    rec["n"] = 3
    rec["i"] = F
    rec["label"] = np.asarray(labels, np.uint8)
    with open(path, "wb") as f:
        f.write(head.encode("ascii"))
        f.write(V.tobytes())
        f.write(rec.tobytes())


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def load_model_triangles(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """The model as triangles (``mst.meshtools.io.load_triangles``), checked for emptiness and NaN."""
    from mst.meshtools.io import load_triangles

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


def face_albedo(V: np.ndarray, F: np.ndarray, lighting, base=(0.80, 0.78, 0.74)) -> np.ndarray:
    """(M, 3) albedo per model triangle so that planes sharing an edge differ in shaded brightness.

    Directional lighting alone cannot separate every pair of adjacent faces (some orientation always
    ties), so each plane gets a grey level from a small palette, chosen greedily (largest planes
    first) to maximise the smallest shaded-brightness difference to its already-coloured neighbours.
    """
    from mst.pipeline.render import _unit, face_normals

    M = len(F)
    pid = plane_ids(V, F)
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
                       "try another --seed, --distance or scenario")
    Xc = V[cand] @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
    uv = cam.project(Xc)
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


# ---------------------------------------------------------------------------- the stage
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
    scene = _resolve(scenario, cfg, lo, hi, cam, focus=focus_point(Vc, F))
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
    floor_kind = "terrain" if scene.scenario == "flyover" else cfg.floor
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


def _check_config(scenario: str, cfg: SynthConfig) -> None:
    bad = []
    if scenario not in SCENARIOS:
        raise InputError(None, f"unknown scenario {scenario!r} (expected one of {', '.join(SCENARIOS)})")
    if cfg.base not in BASE_SCENARIOS:
        bad.append(f"base must be one of {', '.join(BASE_SCENARIOS)}")
    if cfg.frames is not None and cfg.frames < 1:
        bad.append(f"frames must be >= 1 (got {cfg.frames})")
    if cfg.drop is not None and cfg.drop < 1:
        bad.append(f"drop must be >= 1 (got {cfg.drop})")
    if not (cfg.fps > 0 and math.isfinite(cfg.fps)):
        bad.append("fps must be > 0")
    if cfg.width < 16 or cfg.height < 16:
        bad.append("width and height must be >= 16 pixels")
    if cfg.focal_px is not None and not cfg.focal_px > 0:
        bad.append("focal length must be > 0")
    if cfg.distance is not None and not cfg.distance > 0:
        bad.append("distance must be > 0")
    if cfg.speed is not None and not (cfg.speed >= 0 and math.isfinite(cfg.speed)):
        bad.append("speed must be >= 0")
    if cfg.floor not in ("concrete", "tiles"):
        bad.append("floor must be 'concrete' or 'tiles'")
    if cfg.depth_noise not in ("none", "kinect"):
        bad.append("depth noise must be 'none' or 'kinect'")
    if cfg.rgb_noise < 0 or cfg.click_noise < 0:
        bad.append("noise levels must be >= 0")
    if cfg.motion_blur < 1:
        bad.append("motion blur must be >= 1 sub-frame")
    if cfg.aa_samples not in (0, 4, 8, 16):
        bad.append("aa samples must be 0, 4, 8 or 16")
    if cfg.n_clicks < 4:
        bad.append("n_clicks must be >= 4")
    if cfg.up not in UP_AXES:
        bad.append(f"up must be one of {', '.join(UP_AXES)}")
    if cfg.texture_size < 64 or cfg.texture_size & (cfg.texture_size - 1):
        bad.append("texture size must be a power of two >= 64")
    if bad:
        raise InputError(None, "; ".join(bad))


def _prepare_out_dir(out_dir: Path, overwrite: bool) -> Path:
    """A fresh temporary folder beside ``out_dir`` (renamed onto it at the end)."""
    out_dir = Path(out_dir)
    parent = out_dir.resolve().parent
    if not parent.is_dir():
        raise InputError(out_dir, "parent folder does not exist")
    if out_dir.exists():
        if not out_dir.is_dir():
            raise InputError(out_dir, "output exists and is not a folder")
        if any(out_dir.iterdir()) and not overwrite:
            raise InputError(out_dir, "output folder is not empty (use --overwrite)")
    return Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".tmp", dir=parent))


_OWNED = ("rgb", "depth", "cMo", "video.mp4", "camera.json", "gt.txt", "clicks.txt", "model.obj", "scene.ply",
          "scene.json", "frames.csv")


def _commit_out_dir(tmp: Path, out_dir: Path) -> None:
    """Move the finished sequence into place (replacing only the files a sequence folder holds)."""
    out_dir = Path(out_dir)
    if out_dir.exists() and not any(out_dir.iterdir()):
        out_dir.rmdir()
    if not out_dir.exists():
        os.replace(tmp, out_dir)
        return
    for name in _OWNED:
        target = out_dir / name
        if target.is_dir():
            shutil.rmtree(target)
        elif target.exists():
            target.unlink()
    for item in tmp.iterdir():
        os.replace(item, out_dir / item.name)
    tmp.rmdir()


def synthesize(scenario: str, model_path: str | os.PathLike, out_dir: str | os.PathLike,
               config: SynthConfig | None = None, progress: Callable[[int], None] | None = None,
               overwrite: bool = False, model_source: str | None = None) -> dict:
    """Render a synthetic sequence of ``model_path`` along ``scenario`` into ``out_dir`` (layout: module doc).

    All outputs appear at once (written in a temporary folder beside ``out_dir``, then moved).
    ``model_source`` is the model path recorded in scene.json (default ``model_path``).
    Returns a summary dict (frames, timings, paths, resolved parameters).
    """
    import time

    import cv2

    from mst.pipeline import render_kernels as rk

    cfg = config or SynthConfig()
    if scenario in ("turntable", "occluder", "blackout"):  # moving object / interrupted view
        from mst.pipeline.synth_dynamic import synthesize_dynamic

        return synthesize_dynamic(scenario, model_path, out_dir, cfg, progress=progress, overwrite=overwrite)
    _check_config(scenario, cfg)
    model_path = Path(model_path)
    V, F = load_model_triangles(model_path)
    t_start = time.perf_counter()
    cam, R_cm, scene, renderer, (V_all, F_all, mat_all) = build_scene(scenario, cfg, V, F)
    t_setup = time.perf_counter() - t_start
    p = scene.params
    frames, drop, fps = p["frames"], p["drop"], float(cfg.fps)
    T_model_canon = make_T(R_cm.T, np.zeros(3))

    def T_model_cam_at(s: float) -> np.ndarray:
        return T_model_canon @ scene.pose(s)

    T_model_cam = np.array([T_model_cam_at(k * drop / fps) for k in range(frames)])
    T_cam_model = inv_T(T_model_cam)
    # clicks on frame 0
    click_idx = choose_clicks(renderer, cam, T_cam_model[0], V, F, cfg.n_clicks)
    X_clk = V[click_idx]
    uv_clk = cam.project(X_clk @ T_cam_model[0][:3, :3].T + T_cam_model[0][:3, 3])
    if cfg.click_noise > 0:
        uv_clk = uv_clk + np.random.default_rng([int(cfg.seed), 3]).normal(0, cfg.click_noise, uv_clk.shape)

    tmp = _prepare_out_dir(Path(out_dir), overwrite)
    n_model_tri = len(F)
    render_s = 0.0
    rows = []
    try:
        (tmp / "rgb").mkdir()
        (tmp / "cMo").mkdir()
        if cfg.depth:
            (tmp / "depth").mkdir()
        writer = None
        if cfg.video:
            writer = cv2.VideoWriter(str(tmp / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                     (cam.width, cam.height))
            if not writer.isOpened():
                raise MstError("cv2.VideoWriter could not open an mp4v writer")
        for k in range(frames):
            t0 = time.perf_counter()
            s_k = k * drop / fps
            out = renderer.render(cam, T_cam_model[k], aa_samples=cfg.aa_samples,
                                  with_cos=cfg.depth and cfg.depth_noise == "kinect")
            rgb = out["rgb"]
            if cfg.motion_blur > 1:
                # average sub-frames over the exposure ending at the frame time (the GT pose)
                acc = rgb.astype(np.float64)
                for j in range(1, cfg.motion_blur):
                    s_j = s_k - cfg.shutter * (j / (cfg.motion_blur - 1)) * drop / fps
                    acc += renderer.render(cam, inv_T(T_model_cam_at(s_j)), aa_samples=cfg.aa_samples)["rgb"]
                rgb = (acc / cfg.motion_blur).astype(np.float32)
            noise = (np.random.default_rng([int(cfg.seed), k, 1]).integers(0, 2**32, rgb.shape, dtype=np.uint32)
                     if cfg.rgb_noise > 0 else np.zeros((0, 0, 0), np.uint32))  # bits of N(0, 1) draws
            bgr = np.empty((cam.height, cam.width, 3), np.uint8)
            rk.encode_bgr8(np.ascontiguousarray(rgb, np.float32), noise, np.float32(cfg.rgb_noise), bgr)
            depth = out["depth"]
            if cfg.depth and cfg.depth_noise == "kinect":
                depth = kinect_depth(depth, out["cos_incidence"], 0.5 * (cam.fx + cam.fy),
                                     np.random.default_rng([int(cfg.seed), k, 2]))
            render_s += time.perf_counter() - t0
            cv2.imwrite(str(tmp / "rgb" / f"{k:06d}.png"), bgr)
            if writer is not None:
                writer.write(bgr)
            if cfg.depth:
                mm = np.empty(depth.shape, np.uint16)
                rk.depth_to_mm(np.ascontiguousarray(depth, np.float32), mm)
                cv2.imwrite(str(tmp / "depth" / f"{k:06d}.png"), mm)
                np.save(tmp / "depth" / f"{k:06d}.npy", depth.astype(np.float32))
            (tmp / "cMo" / f"{k:06d}.txt").write_text(
                "".join(" ".join(f"{v:.15g}" for v in row) + "\n" for row in T_cam_model[k]))
            ids = out["ids"]
            model_px = int(np.count_nonzero((ids >= 0) & (ids < n_model_tri)))
            rows.append((k, k / fps, model_px, out["n_edge_px"]))
            if progress:
                progress(1)
        if writer is not None:
            writer.release()
        # ground truth and metadata
        (tmp / "gt.txt").write_text(
            "# mst synth ground truth: camera pose in the model frame (TUM: t tx ty tz qx qy qz qw), t = frame / fps\n"
            + format_tum(np.arange(frames) / fps, T_model_cam))
        write_camera(tmp / "camera.json", cam)
        (tmp / "clicks.txt").write_text(
            "# mst synth clicks for frame 0: X Y Z (model frame, metres) u v (pixels)"
            + (f", pixel noise sigma {cfg.click_noise:g}" if cfg.click_noise > 0 else "") + "\n"
            + "".join(f"{X[0]:.9f} {X[1]:.9f} {X[2]:.9f} {uv[0]:.4f} {uv[1]:.4f}\n" for X, uv in zip(X_clk, uv_clk)))
        from mst.meshtools.io import save_triangles

        save_triangles(tmp / "model.obj", V, F)  # shortest round-trip text: float64 vertices exact
        write_ply_mesh(tmp / "scene.ply", V_all, F_all, mat_all)
        (tmp / "frames.csv").write_text("frame,time,model_px,edge_px\n"
                                        + "".join(f"{k},{t:.6f},{m},{e}\n" for k, t, m, e in rows))
        spec = {
            "format": "mst-synth-scene", "version": SCENE_VERSION, "mst_version": __version__,
            "scenario": scenario, "seed": int(cfg.seed), "config": asdict(cfg),
            "model": {"source": str(model_source if model_source is not None else model_path), "file": "model.obj",
                      "sha256": _sha256(tmp / "model.obj"), "vertices": len(V), "triangles": len(F)},
            "camera": cam.to_dict(), "resolved": scene.params,
        }
        (tmp / "scene.json").write_text(json.dumps(spec, indent=2) + "\n")
        _commit_out_dir(tmp, Path(out_dir))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    model_frac = np.array([r[2] for r in rows]) / float(cam.width * cam.height)
    return {
        "out_dir": str(out_dir), "scenario": scenario, "base": p["base"], "frames": frames, "drop": drop, "fps": fps,
        "width": cam.width, "height": cam.height, "focal_px": cam.fx, "depth": bool(cfg.depth),
        "distance_m": p["distance"], "speed_m_s": p["speed"], "clicks": len(X_clk),
        "frames_without_model": int(np.count_nonzero(model_frac == 0)),
        "triangles": {"model": len(F), "scene": len(F_all)},
        "setup_s": t_setup, "render_ms_per_frame": 1000.0 * render_s / max(frames, 1),
        "total_s": time.perf_counter() - t_start,
    }


#: the scene.json layout this mst writes and reads (a file of another version is refused, never guessed)
SCENE_VERSION = 1


def synthesize_from_scene(scene_json: str | os.PathLike, out_dir: str | os.PathLike,
                          progress: Callable[[int], None] | None = None, overwrite: bool = False) -> dict:
    """Re-render a sequence from its ``scene.json`` (and the ``model.obj`` beside it): identical files."""
    p = Path(scene_json)
    if not p.is_file():
        raise InputError(p, "scene file does not exist")
    try:
        spec = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(p, f"not valid JSON ({e})") from None
    if not isinstance(spec, dict) or spec.get("format") != "mst-synth-scene":
        raise InputError(p, "not an mst synth scene.json (no 'format': 'mst-synth-scene')")
    if spec.get("version") != SCENE_VERSION:
        raise InputError(p, f"scene.json version {spec.get('version')!r} is not the one this mst reads "
                            f"({SCENE_VERSION}); re-render it with the mst that wrote it")
    try:
        cfg = SynthConfig.from_dict(spec["config"])
        scenario = spec["scenario"]
        model = spec["model"]
    except (KeyError, TypeError, ValueError) as e:
        raise InputError(p, f"bad scene file ({e})") from None
    mp = p.parent / model.get("file", "model.obj")
    if not mp.is_file():
        raise InputError(mp, "model file named in scene.json does not exist")
    if model.get("sha256") and _sha256(mp) != model["sha256"]:
        raise InputError(mp, "model.obj does not match the sha256 recorded in scene.json")
    return synthesize(scenario, mp, out_dir, cfg, progress=progress, overwrite=overwrite,
                      model_source=model.get("source"))
