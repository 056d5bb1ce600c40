"""Synth scenarios: the camera trajectories and rooms of ``orbit``, ``corridor`` and ``flyover``
(and ``fast``, any of them with frames dropped), designed in a canonical frame whose +z is up."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from mst.core.camera import Camera
from mst.core.poses import look_at
from mst.pipeline.synth.config import (
    BASE_SCENARIOS,
    CEILING,
    DEFAULT_FRAMES,
    FLOOR,
    UP_AXES,
    WALL,
    SynthConfig,
)
from mst.pipeline.synth.scenarios_uav import UAV_SCENARIOS, resolve_uav, uav_pose


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
        if self.scenario in UAV_SCENARIOS:
            return uav_pose(self.scenario, p, s)
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
             focus: np.ndarray | None = None, Vc: np.ndarray | None = None) -> Scene:
    """Scenario geometry from the model's canonical bounding box ``[lo, hi]`` and the camera.

    ``focus``: the point a flyover looks at (default: the bounding-box centre); ``Vc``: the model's
    vertices in the canonical frame (uav/fpv: the buildings' south edge along the pass)."""
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
    elif base in UAV_SCENARIOS:
        fc = c if focus is None else np.array([focus[0], focus[1], c[2]])
        p["center"] = fc.tolist()
        q, env = resolve_uav(base, cfg, lo, hi, fc, Vc, duration, FLOOR)
        p.update(q)
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
