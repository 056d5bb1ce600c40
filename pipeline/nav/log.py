"""Navigation logs (GPS + AHRS): the ``nav.csv`` format, strict reading, and a seeded simulator.

Frames and conventions (the same as :func:`mst.pipeline.init_pose.pose_from_gps`):

* **world** frame: east/north/up (ENU), metres. ``nav.csv`` positions are in this frame, either as
  columns ``x,y,z`` or as ``easting,northing,height`` from which an ``offset`` (E0 N0 H0) is
  subtracted (a ``# offset: E0 N0 H0`` header line, or the caller's value).
* **model** frame: the frame of the 3D model and of the vision trajectory (TUM files, ``T_model_cam``).
  ``T_world_model`` maps it into the world frame (identity when the model is georeferenced).
* **body** (platform) frame: x forward, y left, z up; attitude ``R_world_body = Rz(yaw) Ry(-pitch)
  Rx(roll)``: yaw counter-clockwise from east, pitch positive nose up, roll positive right side down.
  The GPS antenna is the body origin.
* **camera** frame: x right, y down, z forward. ``T_body_cam`` is the camera mount: its rotation
  ``R_body_cam = R_ypr(mount) @ R_MOUNT_CAM`` (a mount of yaw/pitch/roll 0 looks forward) and the
  lever arm (camera position in the body frame, metres).

``nav.csv``: one header row ``t,x,y,z,yaw,pitch,roll[,fix]`` (or ``easting,northing,height``),
times in seconds strictly increasing, angles in degrees; ``fix`` (optional, default 1) is 0 for rows
without a GPS position (a dropout: the position columns are ignored, the attitude is used).
``#`` lines are comments.
"""

from __future__ import annotations

import csv
import io
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from mst import InputError
from mst.core.config import Config, param

#: camera axes (x right, y down, z forward) in a mount frame (x forward, y left, z up)
R_MOUNT_CAM = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])

POS_COLUMNS = (("x", "y", "z"), ("easting", "northing", "height"))
ATT_COLUMNS = ("yaw", "pitch", "roll")


# ------------------------------------------------------------------------------ angles
def R_from_ypr_deg(ypr_deg: np.ndarray) -> np.ndarray:
    """(..., 3) yaw/pitch/roll [deg] -> (..., 3, 3) ``Rz(yaw) @ Ry(-pitch) @ Rx(roll)``."""
    a = np.radians(np.asarray(ypr_deg, dtype=np.float64))
    y, p, r = -a[..., 1], a[..., 0], a[..., 2]  # p: yaw, y: -pitch (rotation about +y)
    cz, sz, cy, sy, cx, sx = np.cos(p), np.sin(p), np.cos(y), np.sin(y), np.cos(r), np.sin(r)
    R = np.empty(a.shape[:-1] + (3, 3))
    R[..., 0, 0] = cz * cy
    R[..., 0, 1] = cz * sy * sx - sz * cx
    R[..., 0, 2] = cz * sy * cx + sz * sx
    R[..., 1, 0] = sz * cy
    R[..., 1, 1] = sz * sy * sx + cz * cx
    R[..., 1, 2] = sz * sy * cx - cz * sx
    R[..., 2, 0] = -sy
    R[..., 2, 1] = cy * sx
    R[..., 2, 2] = cy * cx
    return R


def ypr_deg_from_R(R: np.ndarray) -> np.ndarray:
    """Inverse of :func:`R_from_ypr_deg`: (..., 3, 3) -> (..., 3) yaw/pitch/roll [deg]."""
    R = np.asarray(R, dtype=np.float64)
    yaw = np.arctan2(R[..., 1, 0], R[..., 0, 0])
    pitch = np.arcsin(np.clip(R[..., 2, 0], -1.0, 1.0))  # = -(rotation about y)
    roll = np.arctan2(R[..., 2, 1], R[..., 2, 2])
    return np.degrees(np.stack([yaw, pitch, roll], axis=-1))


def mount_T_body_cam(mount_ypr_deg, lever_arm_m) -> np.ndarray:
    """4x4 ``T_body_cam`` from a mount yaw/pitch/roll [deg] and a lever arm [m, body frame]."""
    T = np.eye(4)
    T[:3, :3] = R_from_ypr_deg(np.asarray(mount_ypr_deg, float)) @ R_MOUNT_CAM
    T[:3, 3] = np.asarray(lever_arm_m, float)
    return T


def mount_ypr_deg_from_R(R_body_cam: np.ndarray) -> np.ndarray:
    """Mount yaw/pitch/roll [deg] of a ``R_body_cam`` (inverse of the rotation of :func:`mount_T_body_cam`)."""
    return ypr_deg_from_R(np.asarray(R_body_cam) @ R_MOUNT_CAM.T)


def check_rotation(R: np.ndarray, path: str | os.PathLike | None, what: str = "mount rotation", tol: float = 1e-3) -> np.ndarray:
    """Return ``R`` (3x3) re-orthonormalised, or raise :class:`mst.InputError` if it is not a rotation."""
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.isfinite(R).all():
        raise InputError(path, f"{what} must be 3x3 finite numbers")
    err = np.abs(R.T @ R - np.eye(3)).max()
    det = np.linalg.det(R)
    if err > tol or abs(det - 1.0) > tol:
        raise InputError(path, f"{what} is not a rotation (|R^T R - I| = {err:.3g}, det = {det:.4g})")
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt


def read_mount_rotation(path: str | os.PathLike) -> np.ndarray:
    """Read a camera-mount rotation ``R_body_cam``: 9 numbers (3x3 row-major) or 4 (quaternion qx qy qz qw).

    ``#`` comments, commas and brackets allowed. Raises :class:`mst.InputError` naming the file when
    it is missing, holds another count of numbers, or is not a rotation (not orthonormal, a
    reflection, or a quaternion whose norm is not 1 within 1e-3).
    """
    from mst.core.poses import read_numbers

    p = Path(path)
    a = read_numbers(p, "mount rotation file")  # UTF-8 checked, NaN/inf refused, the line of a bad number
    if len(a) == 9:
        return check_rotation(a.reshape(3, 3), p)
    if len(a) == 4:
        n = np.linalg.norm(a)
        if abs(n - 1.0) > 1e-3:
            raise InputError(p, f"mount quaternion has norm {n:.4g}, not 1: not a rotation")
        from mst.core.poses import R_from_quat

        return R_from_quat(a)
    raise InputError(p, f"{len(a)} numbers: expected 9 (3x3 rotation) or 4 (quaternion qx qy qz qw)")


# ------------------------------------------------------------------------------ the log
@dataclass
class NavLog:
    """A GPS/AHRS log. ``t`` (N,) s, strictly increasing; ``p_world`` (N, 3) m, GPS antenna in the
    world frame (offset removed); ``ypr_deg`` (N, 3) platform attitude; ``fix`` (N,) bool, False where
    the GPS has no position (dropout); ``offset`` (3,) the E/N/H subtracted from the file's values."""

    t: np.ndarray
    p_world: np.ndarray
    ypr_deg: np.ndarray
    fix: np.ndarray
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def R_world_body(self) -> np.ndarray:
        """(N, 3, 3) platform attitude."""
        return R_from_ypr_deg(self.ypr_deg)


def read_navlog(path: str | os.PathLike, offset: tuple[float, float, float] | None = None) -> NavLog:
    """Read and validate ``nav.csv`` (format in the module docstring).

    Raises :class:`mst.InputError` naming the file and the problem for: a missing file, no header or
    no rows, missing columns, non-numbers, NaN/infinite values, unsorted or duplicate times, a ``fix``
    value other than 0/1, angles out of range (|pitch| > 90, |yaw|/|roll| > 360).
    """
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "navigation log does not exist")
    text = p.read_text(errors="replace")
    header_offset = None
    lines = []
    for line in text.splitlines():
        s = line.strip()
        if s.startswith("#"):
            body = s[1:].strip()
            if body.lower().startswith("offset:"):
                try:
                    header_offset = np.array([float(v) for v in body.split(":", 1)[1].replace(",", " ").split()])
                except ValueError:
                    raise InputError(p, f"bad offset line {s!r}") from None
                if header_offset.shape != (3,) or not np.isfinite(header_offset).all():
                    raise InputError(p, f"offset line needs 3 finite numbers E N H: {s!r}")
            continue
        if s:
            lines.append(s)
    if not lines:
        raise InputError(p, "navigation log is empty (no header row)")
    rows = list(csv.reader(io.StringIO("\n".join(lines))))
    header = [h.strip().lower() for h in rows[0]]
    pos_cols = next((c for c in POS_COLUMNS if all(k in header for k in c)), None)
    need = ["t", *(pos_cols or POS_COLUMNS[0]), *ATT_COLUMNS]
    missing = [k for k in need if k not in header]
    if missing:
        raise InputError(p, f"missing column(s) {', '.join(missing)} (header: {','.join(header)}; need "
                            "t,x,y,z,yaw,pitch,roll or t,easting,northing,height,yaw,pitch,roll [,fix])")
    if len(rows) < 2:
        raise InputError(p, "navigation log has a header but no rows")
    cols = need + (["fix"] if "fix" in header else [])
    idx = [header.index(k) for k in cols]
    data = np.empty((len(rows) - 1, len(cols)))
    for i, r in enumerate(rows[1:]):
        if len(r) != len(header):
            raise InputError(p, f"row {i + 1}: {len(r)} fields, header has {len(header)}")
        try:
            data[i] = [float(r[j]) for j in idx]
        except ValueError:
            raise InputError(p, f"row {i + 1}: not a number") from None
    bad = ~np.isfinite(data)
    if bad.any():
        i, j = np.argwhere(bad)[0]
        raise InputError(p, f"row {i + 1}: column {cols[j]} is NaN or infinite ({int(bad.any(axis=1).sum())} such rows)")
    t = data[:, 0]
    dt = np.diff(t)
    if (dt == 0).any():
        i = int(np.argmax(dt == 0))
        raise InputError(p, f"duplicate time {t[i]:.6f} s (rows {i + 1} and {i + 2})")
    if (dt < 0).any():
        i = int(np.argmax(dt < 0))
        raise InputError(p, f"times are not sorted: row {i + 2} ({t[i + 1]:.6f} s) comes after {t[i]:.6f} s")
    ypr = data[:, 4:7]
    if (np.abs(ypr[:, 1]) > 90).any():
        raise InputError(p, f"pitch outside [-90, 90] deg in row {int(np.argmax(np.abs(ypr[:, 1]) > 90)) + 1}")
    if (np.abs(ypr[:, [0, 2]]) > 360).any():
        raise InputError(p, "yaw or roll outside [-360, 360] deg (radians instead of degrees?)")
    if "fix" in cols:
        f = data[:, 7]
        if not np.isin(f, (0.0, 1.0)).all():
            raise InputError(p, "column fix must be 0 or 1")
        fix = f == 1.0
    else:
        fix = np.ones(len(t), bool)
    off = np.zeros(3)
    if pos_cols == POS_COLUMNS[1]:
        off = np.asarray(offset, float) if offset is not None else (header_offset if header_offset is not None else off)
    elif offset is not None and np.any(offset):
        raise InputError(p, "an offset applies to easting,northing,height columns, this log has x,y,z")
    return NavLog(t=t, p_world=data[:, 1:4] - off, ypr_deg=ypr, fix=fix, offset=off)


def format_navlog(nav: NavLog, enh: bool = False, comments: list[str] | None = None) -> str:
    """CSV text of a log; ``enh``: easting/northing/height columns with the log's offset added back."""
    out = io.StringIO()
    for c in comments or []:
        out.write(f"# {c}\n")
    if enh:
        out.write("# offset: " + " ".join(f"{v:.3f}" for v in nav.offset) + "\n")
        out.write("t,easting,northing,height,yaw,pitch,roll,fix\n")
        P = nav.p_world + nav.offset
    else:
        out.write("t,x,y,z,yaw,pitch,roll,fix\n")
        P = nav.p_world
    P = np.where(nav.fix[:, None], P, 0.0)
    for ti, pi, ai, fi in zip(nav.t, P, nav.ypr_deg, nav.fix):
        out.write(f"{ti:.6f},{pi[0]:.4f},{pi[1]:.4f},{pi[2]:.4f},{ai[0]:.4f},{ai[1]:.4f},{ai[2]:.4f},{int(fi)}\n")
    return out.getvalue()


# ------------------------------------------------------------------------------ simulator
@dataclass
class NavSimConfig(Config):
    """Error model of :func:`simulate_nav` (seeded; defaults: a consumer UAV, as in the UAV paper)."""

    rate_hz: float = param(5.0, min=0, min_open=True, max=100, help="GPS/AHRS rows per second (1-10 Hz)")
    sigma_h_m: float = param(3.0, min=0, help="GPS white noise, each horizontal axis, m")
    sigma_v_m: float = param(5.0, min=0, help="GPS white noise, vertical, m")
    bias_rw_m_per_sqrt_s: float = param(0.05, min=0, help="GPS bias random walk (each axis), m / sqrt(s)")
    outlier_rate: float = param(0.02, min=0, max=1, help="share of GPS fixes hit by multipath")
    outlier_m: tuple[float, float] = param((15.0, 40.0), min=0, help="multipath error magnitude range, m")
    dropouts: int = param(1, min=0, help="GPS dropouts (fix = 0, attitude still logged)")
    dropout_s: tuple[float, float] = param((5.0, 10.0), min=0, help="their duration range, s")
    ahrs_sigma_deg: float = param(3.0, min=0, help="AHRS white noise, each of yaw/pitch/roll, deg")
    ahrs_yaw_bias_deg: float = param(2.0, help="constant AHRS heading bias, deg")
    mount_ypr_deg: tuple[float, float, float] = param((60.0, -20.0, 0.0), help="camera mount yaw/pitch/roll, deg "
                                                                              "(60 deg pan, 20 deg down)")
    lever_arm_m: tuple[float, float, float] = param((0.10, 0.0, -0.15), help="camera in the body frame, m")
    world_yaw_deg: float = param(0.0, help="T_world_model: rotation about up, deg")
    world_offset_m: tuple[float, float, float] = param((0.0, 0.0, 0.0), help="T_world_model: translation, m")
    enh_offset_m: tuple[float, float, float] | None = param(None, help="write easting/northing/height with this offset, m")
    time_offset_s: float = param(0.0, min=-60, max=60,
                                 help="clock offset of the log: a row measured at video time t is stamped t - offset, s")
    seed: int = param(0, help="seed of the errors")


@dataclass
class NavSimResult:
    """A simulated log and the truth behind it (``T_world_model``, ``T_body_cam``, biases)."""

    nav: NavLog
    T_world_model: np.ndarray
    T_body_cam: np.ndarray
    gps_bias_m: np.ndarray          # (N, 3) the random-walk bias at each row
    outlier: np.ndarray             # (N,) bool
    config: NavSimConfig

    def to_json(self) -> dict:
        """Truth summary (what `mst nav simulate` writes to ``nav_truth.json``)."""
        return {
            "rows": int(len(self.nav.t)), "fixes": int(self.nav.fix.sum()), "outliers": int(self.outlier.sum()),
            "T_world_model": self.T_world_model.tolist(), "T_body_cam": self.T_body_cam.tolist(),
            "mount_ypr_deg": list(self.config.mount_ypr_deg), "lever_arm_m": list(self.config.lever_arm_m),
            "ahrs_yaw_bias_deg": self.config.ahrs_yaw_bias_deg, "time_offset_s": self.config.time_offset_s,
            # the mount a fusion can see: a constant AHRS heading bias b is indistinguishable from a
            # mount yaw of -b for a near-level platform (R_body_cam seen = Rz(-b) R_body_cam)
            "effective_mount_ypr_deg": mount_ypr_deg_from_R(
                R_from_ypr_deg(np.array([-self.config.ahrs_yaw_bias_deg, 0.0, 0.0])) @ self.T_body_cam[:3, :3]).tolist(),
            "gps_bias_mean_m": self.gps_bias_m[self.nav.fix].mean(axis=0).tolist() if self.nav.fix.any() else None,
            "config": self.config.to_dict(),
        }


def interpolate_poses(t_src: np.ndarray, T_src: np.ndarray, t_new: np.ndarray) -> np.ndarray:
    """Poses (N, 4, 4) at times ``t_src`` (increasing) -> (M, 4, 4) at ``t_new`` (clipped to the range):
    linear positions, slerped rotations."""
    from scipy.spatial.transform import Rotation, Slerp

    tn = np.clip(t_new, t_src[0], t_src[-1])
    out = np.tile(np.eye(4), (len(tn), 1, 1))
    for k in range(3):
        out[:, k, 3] = np.interp(tn, t_src, T_src[:, k, 3])
    if len(t_src) == 1:
        out[:, :3, :3] = T_src[0, :3, :3]
    else:
        out[:, :3, :3] = Slerp(t_src, Rotation.from_matrix(T_src[:, :3, :3]))(tn).as_matrix()
    return out


def simulate_nav(t_gt: np.ndarray, T_model_cam: np.ndarray, cfg: NavSimConfig | None = None) -> NavSimResult:
    """Simulate a GPS/AHRS log from a ground-truth camera trajectory.

    ``t_gt`` (N,) s and ``T_model_cam`` (N, 4, 4) (e.g. ``mst synth``'s ``gt.txt``). The platform is
    ``T_world_body = T_world_model @ T_model_cam @ inv(T_body_cam)``; rows at ``cfg.rate_hz`` over the
    ground-truth time range. GPS: antenna position + white noise (sigma_h, sigma_h, sigma_v) + a
    random-walk bias + multipath outliers (random direction, magnitude in ``outlier_m``) and
    ``dropouts`` stretches with fix = 0. AHRS: yaw/pitch/roll + white noise + a constant yaw bias.
    """
    from mst.core.poses import inv_T, make_T

    cfg = cfg or NavSimConfig()
    rng = np.random.default_rng(cfg.seed)
    t = np.arange(t_gt[0], t_gt[-1] + 1e-9, 1.0 / cfg.rate_hz)
    T_mc = interpolate_poses(t_gt, T_model_cam, t)
    c, s = np.cos(np.radians(cfg.world_yaw_deg)), np.sin(np.radians(cfg.world_yaw_deg))
    T_wm = make_T(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.asarray(cfg.world_offset_m, float))
    T_bc = mount_T_body_cam(cfg.mount_ypr_deg, cfg.lever_arm_m)
    T_wb = T_wm @ T_mc @ inv_T(T_bc)
    n = len(t)
    sig = np.array([cfg.sigma_h_m, cfg.sigma_h_m, cfg.sigma_v_m])
    dt = 1.0 / cfg.rate_hz
    bias = np.cumsum(rng.normal(0.0, cfg.bias_rw_m_per_sqrt_s * np.sqrt(dt), (n, 3)), axis=0)
    gps = T_wb[:, :3, 3] + bias + rng.normal(0.0, 1.0, (n, 3)) * sig
    outlier = rng.random(n) < cfg.outlier_rate
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    gps[outlier] += d[outlier] * rng.uniform(*cfg.outlier_m, size=(n, 1))[outlier]
    fix = np.ones(n, bool)
    span = t[-1] - t[0]
    for _ in range(cfg.dropouts):
        dur = rng.uniform(*cfg.dropout_s)
        if span <= dur + 2.0:
            break
        t0 = t[0] + 1.0 + rng.uniform(0.0, span - dur - 2.0)
        fix[(t >= t0) & (t < t0 + dur)] = False
    ypr = ypr_deg_from_R(T_wb[:, :3, :3]) + rng.normal(0.0, cfg.ahrs_sigma_deg, (n, 3))
    ypr[:, 0] = (ypr[:, 0] + cfg.ahrs_yaw_bias_deg + 180.0) % 360.0 - 180.0
    ypr[:, 1] = np.clip(ypr[:, 1], -90.0, 90.0)
    off = np.asarray(cfg.enh_offset_m, float) if cfg.enh_offset_m is not None else np.zeros(3)
    nav = NavLog(t=t - cfg.time_offset_s, p_world=gps, ypr_deg=ypr, fix=fix, offset=off)
    return NavSimResult(nav=nav, T_world_model=T_wm, T_body_cam=T_bc, gps_bias_m=bias, outlier=outlier & fix, config=cfg)


def write_sim_outputs(res: NavSimResult, nav_path: str | os.PathLike, truth_path: str | os.PathLike | None) -> None:
    """Write ``nav.csv`` and (optionally) the truth JSON (call inside :func:`mst.atomic_outputs`)."""
    cfg = res.config
    comments = [f"mst nav simulate (seed {cfg.seed}): GPS sigma {cfg.sigma_h_m}/{cfg.sigma_v_m} m, AHRS sigma "
                f"{cfg.ahrs_sigma_deg} deg, {cfg.rate_hz} Hz",
                "t [s], GPS antenna position in the world frame (ENU, m), platform yaw/pitch/roll [deg], fix 0/1"]
    Path(nav_path).write_text(format_navlog(res.nav, enh=cfg.enh_offset_m is not None, comments=comments))
    if truth_path is not None:
        Path(truth_path).write_text(json.dumps(res.to_json(), indent=2) + "\n")
