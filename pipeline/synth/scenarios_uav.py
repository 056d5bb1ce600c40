"""UAV scenarios of ``mst synth`` (issue 11): a survey pass with a camera pitched down, and an FPV
facade pass, over a city model (CityJSON, a procedural :func:`mst.meshtools.generate.city_block_model`).

Both are designed in the canonical frame (z up, metres, seconds) like :mod:`.scenarios`:

* ``uav``: a survey UAV at ``distance`` metres above the ground (default 60; the issue's 30-120 m)
  flies along +x outside the block's south edge (the lowest y of the model near the focus), its
  gimbal looking north at the buildings, pitched ``pitch_deg`` below the horizon (default 45; 30-60).
  Turns: the camera sways +-12 deg about the view direction; the UAV slows to a hover (from 20 %
  of the duration) and over 25-42 % turns 135 deg on the spot to look south-east, away from the
  block (open textured ground only: no building in view for about 35-65 % of the sequence), turns
  back over 58-75 % and flies on (from 80 %) past the buildings it saw before the turn.
* ``fpv``: a forward-looking FPV camera (pitched ``pitch_deg`` down, default 8) flying along +x at
  ``distance`` metres (default 30; 20-50) south of the buildings' facades, at 60 % of the model's
  height (at least 5 m), yawed 40 deg from the flight direction toward the facades, banking
  (+-4 deg roll) through an S-turn of +-15 deg yaw.

The south edge is measured on the model's vertices within the pass's x range (``Vc``), so that a
sparse city (a few buildings in a large bounding box) is passed at the stated distance.
"""

from __future__ import annotations

import math

import numpy as np

from mst.core.poses import look_at

UAV_SCENARIOS = ("uav", "fpv")
DEFAULT_FRAMES_UAV = {"uav": 240, "fpv": 150}
UAV_DEFAULTS = {"uav": {"distance": 60.0, "pitch_deg": 45.0}, "fpv": {"distance": 30.0, "pitch_deg": 8.0}}
#: the ``uav`` look-away stretch, fractions of the duration: turn away, away (no building in view), back
GAP_PHASES = (0.25, 0.42, 0.58, 0.75)
#: how far the camera turns away from the block (deg): its 62 deg wide view (at 525 px per 640) then
#: points 14-76 deg south of the flight line, and every building lies north of it
AWAY_DEG = 135.0


def _along(u: float, p: dict) -> float:
    """Distance flown (metres) at duration fraction ``u``: ``speed`` except for a hover (speed
    ramped to 0 over [g0 - 0.05, g0] and back over [g3, g3 + 0.05]) around the look-away turn."""
    g0, _, _, g3 = p["gap_phases"]
    uu = np.linspace(0.0, 1.0, 4001)
    v = 1.0 - np.array([_smoothstep(g0 - 0.05, g0, x) - _smoothstep(g3, g3 + 0.05, x) for x in uu])
    dist = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(uu))]) * p["speed"] * p["duration"]
    return float(np.interp(u, uu, dist))


def _smoothstep(a: float, b: float, x: float) -> float:
    s = min(max((x - a) / (b - a), 0.0), 1.0)
    return s * s * (3 - 2 * s)


def _ground(c: np.ndarray, G: float, z: float, material: int):
    """One upward ground quad of half-size ``G`` around ``c`` at height ``z``: [(V, F, material)]."""
    V = np.array([[c[0] - G, c[1] - G, z], [c[0] + G, c[1] - G, z], [c[0] + G, c[1] + G, z], [c[0] - G, c[1] + G, z]])
    return [(V, np.array([[0, 1, 2], [0, 2, 3]]), material)]


def south_edge(Vc: np.ndarray | None, lo: np.ndarray, x0: float, x1: float) -> float:
    """The lowest y of the model's vertices with x in [x0, x1] (canonical frame); ``lo[1]`` if none."""
    if Vc is None:
        return float(lo[1])
    sel = (Vc[:, 0] >= x0) & (Vc[:, 0] <= x1)
    return float(Vc[sel, 1].min()) if np.any(sel) else float(lo[1])


def resolve_uav(base: str, cfg, lo: np.ndarray, hi: np.ndarray, fc: np.ndarray, Vc: np.ndarray | None,
                duration: float, floor_material: int) -> tuple[dict, list]:
    """Trajectory parameters (JSON-able, into scene.json) and the ground of a ``uav``/``fpv`` pass."""
    d = UAV_DEFAULTS[base]
    D = float(cfg.distance or d["distance"])
    pitch = float(cfg.pitch_deg if cfg.pitch_deg is not None else d["pitch_deg"])
    height = float(hi[2] - lo[2])
    if base == "uav":
        speed = float(cfg.speed if cfg.speed is not None else max(6.0, D / 6.0))
        length = _along(1.0, {"gap_phases": GAP_PHASES, "speed": speed, "duration": duration})
        x0 = fc[0] - 0.5 * length
        eye_z = lo[2] + D
        # the image centre hits the ground/buildings 40 % of the look distance inside the south edge
        look = max(eye_z - (lo[2] + 0.3 * height), 1.0) / math.tan(math.radians(pitch))
        y_edge = south_edge(Vc, lo, x0 - 0.5 * look, x0 + length + 0.5 * look)
        p = dict(distance=D, pitch_deg=pitch, speed=speed, path_length=length, x_start=x0,
                 eye_y=y_edge - 0.6 * look, eye_z=eye_z, look_m=look, gap_phases=list(GAP_PHASES))
        G = 0.5 * length + 6 * look + 0.5 * float(np.linalg.norm(hi[:2] - lo[:2]))
        p["texture_distance"] = look / math.cos(math.radians(pitch))
    else:  # fpv
        speed = float(cfg.speed if cfg.speed is not None else 10.0)
        length = speed * duration
        x0 = fc[0] - 0.5 * length
        eye_z = lo[2] + max(5.0, 0.6 * height)
        y_edge = south_edge(Vc, lo, x0, x0 + length + 2 * D)
        p = dict(distance=D, pitch_deg=pitch, speed=speed, path_length=length, x_start=x0,
                 eye_y=y_edge - D, eye_z=eye_z, yaw_to_facade_deg=40.0)
        G = 0.5 * length + 20 * D + 0.5 * float(np.linalg.norm(hi[:2] - lo[:2]))
        p["texture_distance"] = 1.3 * D
    env = _ground(fc, G, float(lo[2]), floor_material) if cfg.environment else []
    p["room"] = [fc[0] - G, fc[1] - G, float(lo[2]), fc[0] + G, fc[1] + G, float(lo[2])]
    return p, env


def uav_pose(base: str, p: dict, s: float) -> np.ndarray:
    """Camera pose ``T_canon_cam`` of a ``uav``/``fpv`` pass at time ``s`` (seconds)."""
    T = p["duration"]
    u = s / T if T > 0 else 0.0
    x = p["x_start"] + (_along(u, p) if base == "uav" else p["speed"] * s)
    pitch = math.radians(p["pitch_deg"])
    if base == "uav":
        g0, g1, g2, g3 = p["gap_phases"]
        away = _smoothstep(g0, g1, u) - _smoothstep(g2, g3, u)  # 1: looking south, away from the block
        yaw = math.pi / 2 + math.radians(12.0) * math.sin(2 * math.pi * s / 5.0) - math.radians(AWAY_DEG) * away
        eye = np.array([x, p["eye_y"], p["eye_z"] + 0.01 * p["distance"] * math.sin(2 * math.pi * s / 4.0)])
        roll = 2.0 * math.sin(2 * math.pi * s / 7.0)
    else:
        yaw_s = math.radians(15.0) * math.sin(2 * math.pi * u)  # S-turn
        yaw = math.radians(p["yaw_to_facade_deg"]) + yaw_s
        eye = np.array([x, p["eye_y"] - 0.1 * p["distance"] * math.sin(2 * math.pi * u), p["eye_z"]])
        roll = -4.0 * math.cos(2 * math.pi * u)  # banking into the turn
    fwd = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), -math.sin(pitch)])
    return look_at(eye, eye + fwd, roll_deg=roll)
