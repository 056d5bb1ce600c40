"""Trajectory comparison of ``mst eval traj``: association, alignment, ATE, RPE, the UAV table.

Conventions: poses are ``T_model_cam`` 4x4 float64 (camera pose in the model/world frame, what TUM
files hold); positions in metres, angles in degrees. The computations follow evo (Grupp 2017)
exactly, so the numbers equal ``evo_ape`` / ``evo_rpe`` on the same files:

* association: evo's ``associate_trajectories`` (nearest timestamp within ``t_max_diff`` seconds,
  each pose of the trajectory with fewer poses matched into the longer one);
* alignment of the estimate onto the reference: ``none``; ``se3`` / ``sim3`` (Umeyama on the
  associated positions, without / with scale); ``first`` (the estimate's first associated pose
  mapped onto the reference's: ``T = T_ref[0] @ inv(T_est[0])``);
* ATE: ``|t_est - t_ref|`` per associated pose; rotation error: angle of ``R_est^T R_ref``;
* RPE (consecutive pairs chosen on the aligned estimate like evo): ``E = inv(inv(Q_i) Q_j) inv(P_i) P_j``,
  translation norm and rotation angle, for ``delta`` frames and for ``delta_m`` metres of path;
* statistics: rmse, mean, median, std (population), min, max.

UAV table (mean and std of dX dY dZ and d-yaw): differences estimate - reference of the aligned
positions along the model axes (metres), and of the yaw (degrees, wrapped to (-180, 180], after
removing the constant camera-mount offset ``yaw_offset_deg``). **Yaw of a camera pose**: the heading
of the camera's optical axis (its +z axis) projected on the model XY plane, ``atan2(R[1,2], R[0,2])``
in degrees (0 = +X, 90 = +Y). When the optical axis is within 10 degrees of vertical (nadir camera)
the image-up direction (-y axis of the camera) is projected instead.

Gaps: reference poses that have no estimate within ``t_max_diff`` (tracking lost), counted and listed
as ranges of consecutive reference indices with their times.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mst import InputError, read_text
from mst.core.poses import R_from_quat, check_pose_rows, inv_T, make_T, read_tum, rotation_angle_deg

NADIR_LIMIT_DEG = 10.0


@dataclass
class TrajConfig:
    """Settings of :func:`evaluate_trajectories`."""

    align: str = "se3"              # none | se3 | sim3 | first
    t_max_diff: float = 0.01        # seconds, association tolerance (evo's default)
    t_offset: float = 0.0           # seconds added to the estimate's timestamps
    delta: int = 1                  # RPE step in frames
    delta_m: float = 1.0            # RPE step in metres of path
    yaw_offset_deg: float = 0.0     # constant mount offset removed from d-yaw
    fmt: str = "auto"               # auto | tum | kitti | csv
    csv_columns: str | None = None  # "t=time,x=px,y=py,z=pz,qx=..,qy=..,qz=..,qw=.."
    fps: float | None = None        # timestamps of KITTI files: index / fps (index when None)


# ------------------------------------------------------------------------------------ reading
def read_trajectory(path: str | os.PathLike, fmt: str = "auto", csv_columns: str | None = None,
                    fps: float | None = None, notes: list[str] | None = None) -> tuple[np.ndarray, np.ndarray, bool]:
    """Read a trajectory: ``(t (N,) seconds, T_model_cam (N, 4, 4), has_rotation)``.

    Formats: ``tum`` (``t tx ty tz qx qy qz qw``), ``kitti`` (12 numbers per line, the 3x4 pose
    matrix row-major; time = line index, or index / ``fps``), ``csv`` (a header row; columns named by
    ``csv_columns`` as ``key=column`` pairs for keys t x y z and optionally qx qy qz qw; without
    quaternion columns the rotation is unknown and ``has_rotation`` is False). ``auto``: ``.csv`` is
    CSV, otherwise TUM for 8 numbers per line and KITTI for 12.

    UTF-8 text (a byte-order mark is accepted). Refused with :class:`mst.InputError` naming the
    file (and line): NaN/inf, positions beyond 1e9 m, quaternions that are not unit, timestamps
    out of order, and two poses with the same timestamp that differ (identical duplicates are
    dropped, with a line appended to ``notes``).
    """
    p = Path(path)
    if not p.exists():
        raise InputError(p, "trajectory file does not exist")
    text = read_text(p, "trajectory file")
    if fmt == "auto":
        if p.suffix.lower() == ".csv":
            fmt = "csv"
        else:
            first = next((ln for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")), "")
            fmt = "kitti" if len(first.replace(",", " ").split()) == 12 else "tum"
    if fmt == "tum":
        t, T = read_tum(p)
        has_rot = True
    elif fmt == "kitti":
        rows, lines = [], []
        for ln, line in enumerate(text.splitlines(), 1):
            s = line.split("#", 1)[0].strip()
            if not s:
                continue
            parts = s.split()
            if len(parts) != 12:
                raise InputError(p, f"line {ln}: KITTI poses need 12 numbers per line, got {len(parts)}")
            try:
                rows.append([float(x) for x in parts])
            except ValueError:
                raise InputError(p, f"line {ln}: not a number") from None
            lines.append(ln)
        if not rows:
            raise InputError(p, "trajectory has no poses")
        a = np.asarray(rows)
        check_pose_rows(p, a, np.asarray(lines), quat_cols=None, pos_cols=slice(3, 12, 4))
        T = np.tile(np.eye(4), (len(a), 1, 1))
        T[:, :3, :] = a.reshape(-1, 3, 4)
        # KITTI prints >= 6 significant digits: a rotation block off by more than 1e-2 (or a
        # reflection) is not a rotation; it must not be re-orthonormalised into an arbitrary one
        R = T[:, :3, :3]
        with np.errstate(over="ignore", invalid="ignore"):  # entries of 1e308 overflow: not a rotation
            off = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
            bad = ~(off <= 1e-2) | ~(np.linalg.det(R) > 0)
        if bad.any():
            raise InputError(p, f"line {lines[int(np.argmax(bad))]}: the 3x3 rotation block is not a rotation")
        U, _, Vt = np.linalg.svd(T[:, :3, :3])
        T[:, :3, :3] = U @ Vt
        t = np.arange(len(a), dtype=np.float64) / (fps or 1.0)
        has_rot = True
    elif fmt == "csv":
        t, T, has_rot = _read_csv(p, text, csv_columns)
    else:
        raise InputError(p, f"unknown trajectory format {fmt!r}")
    if not np.isfinite(T).all() or not np.isfinite(t).all():
        raise InputError(p, "trajectory holds NaN or infinite values")
    dt = np.diff(t)
    if len(t) > 1 and (dt < 0).any():
        k = int(np.argmax(dt < 0))
        raise InputError(p, f"timestamps are not sorted in increasing order (pose {k + 2}: {t[k + 1]:.6f} s after "
                            f"{t[k]:.6f} s)")
    dup = np.flatnonzero(dt == 0)
    if len(dup):
        # same time twice: identical poses are a harmless repeat, different ones are a conflict that
        # must not be averaged or picked silently (evo associates one of them at random)
        differ = np.abs(T[dup + 1] - T[dup]).max(axis=(1, 2)) > 1e-9
        if differ.any():
            k = int(dup[np.argmax(differ)])
            raise InputError(p, f"two different poses at the same timestamp {t[k]:.6f} s (poses {k + 1} and {k + 2})")
        keep = np.ones(len(t), bool)
        keep[dup + 1] = False
        t, T = t[keep], T[keep]
        if notes is not None:
            notes.append(f"{p}: {len(dup)} identical duplicate pose(s) dropped")
    return t, T, has_rot


def _read_csv(p: Path, text: str, spec: str | None) -> tuple[np.ndarray, np.ndarray, bool]:
    import csv
    import io

    try:
        rows = [r for r in csv.reader(io.StringIO(text, newline="")) if r and not r[0].lstrip().startswith("#")]
    except csv.Error as e:
        raise InputError(p, f"not a CSV file ({e})") from None
    if len(rows) < 2:
        raise InputError(p, "CSV trajectory needs a header row and at least one pose")
    header = [h.strip() for h in rows[0]]
    mapping = {k: k for k in ("t", "x", "y", "z", "qx", "qy", "qz", "qw")}
    if spec:
        for item in spec.split(","):
            if "=" not in item:
                raise InputError(None, f"--csv-columns: {item!r} is not key=column")
            k, v = (s.strip() for s in item.split("=", 1))
            if k not in mapping:
                raise InputError(None, f"--csv-columns: unknown key {k!r} (use t x y z qx qy qz qw)")
            mapping[k] = v
    missing = [mapping[k] for k in ("t", "x", "y", "z") if mapping[k] not in header]
    if missing:
        raise InputError(p, f"CSV lacks column(s) {', '.join(missing)} (header: {', '.join(header)}); "
                         "name them with --csv-columns t=..,x=..,y=..,z=..")
    has_rot = all(mapping[k] in header for k in ("qx", "qy", "qz", "qw"))
    keys = ["t", "x", "y", "z"] + (["qx", "qy", "qz", "qw"] if has_rot else [])
    cols = [header.index(mapping[k]) for k in keys]
    try:
        a = np.array([[float(r[c]) for c in cols] for r in rows[1:]], np.float64)
    except (ValueError, IndexError):
        raise InputError(p, "CSV row with a missing or non-numeric value") from None
    check_pose_rows(p, a[:, 1:], np.arange(2, len(a) + 2), quat_cols=slice(3, 7) if has_rot else None)
    R = R_from_quat(a[:, 4:8]) if has_rot else np.tile(np.eye(3), (len(a), 1, 1))
    return a[:, 0], make_T(R, a[:, 1:4]), has_rot


# ----------------------------------------------------------------------------------- association
def associate(t_est: np.ndarray, t_ref: np.ndarray, max_diff: float = 0.01, offset_est: float = 0.0
              ) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs ``(i_est, i_ref)`` of associated poses, evo's ``associate_trajectories`` rule.

    The trajectory with fewer poses is matched into the longer one (ties: the reference is the
    shorter), each of its stamps to the nearest stamp within ``max_diff`` seconds (the upper
    neighbour wins only when strictly closer). ``offset_est`` is added to the estimate's stamps.
    """
    te = np.asarray(t_est, np.float64) + offset_est
    tr = np.asarray(t_ref, np.float64)
    est_longer = len(te) > len(tr)
    s1, s2 = (tr, te) if est_longer else (te, tr)
    if len(s1) == 0 or len(s2) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    inrange = (s1 >= s2[0] - max_diff) & (s1 <= s2[-1] + max_diff)
    i2 = np.minimum(np.searchsorted(s2, s1, side="right"), len(s2) - 1)
    ub = s2[i2] - s1
    lb = np.where(i2 > 0, s1 - s2[np.maximum(i2 - 1, 0)], np.inf)
    best = np.where((ub <= max_diff) & (ub < lb), i2, np.where((lb <= max_diff) & (lb <= ub), i2 - 1, -1))
    ok = inrange & (best >= 0)
    i1 = np.nonzero(ok)[0]
    j = best[ok].astype(np.int64)
    return (j, i1) if est_longer else (i1, j)


# ------------------------------------------------------------------------------------ alignment
def umeyama(x: np.ndarray, y: np.ndarray, with_scale: bool) -> tuple[np.ndarray, np.ndarray, float]:
    """Least-squares ``y ~ s R x + t`` for (N, 3) point sets (Umeyama 1991, evo's formulation)."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    n = len(x)
    mx, my = x.mean(0), y.mean(0)
    sigma_x = np.linalg.norm(x - mx) ** 2 / n
    cov = (y - my).T @ (x - mx) / n
    u, d, v = np.linalg.svd(cov)
    if np.count_nonzero(d > np.finfo(d.dtype).eps) < 2:
        raise InputError(None, "degenerate trajectory (positions collinear or identical): cannot align se3/sim3")
    S = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(v) < 0.0:
        S[2, 2] = -1
    R = u @ S @ v
    s = float(np.trace(np.diag(d) @ S) / sigma_x) if with_scale else 1.0
    t = my - s * (R @ mx)
    return R, t, s


def align_estimate(T_est: np.ndarray, T_ref: np.ndarray, mode: str) -> tuple[np.ndarray, np.ndarray, float]:
    """Align associated estimate poses onto the reference: ``(T_est_aligned, T_ref_est (4x4), scale)``.

    The aligned pose is ``T_ref_est @ T_est`` with the translation scaled by ``scale`` first (sim3).
    """
    T_est = np.asarray(T_est, np.float64)
    if mode == "none":
        return T_est.copy(), np.eye(4), 1.0
    if mode == "first":
        T = T_ref[0] @ inv_T(T_est[0])
        return T @ T_est, T, 1.0
    if mode in ("se3", "sim3"):
        if len(T_est) < 3:
            raise InputError(None, f"--align {mode} needs at least 3 associated poses, got {len(T_est)}")
        R, t, s = umeyama(T_est[:, :3, 3], T_ref[:, :3, 3], mode == "sim3")
        Ts = T_est.copy()
        Ts[:, :3, 3] *= s
        T = make_T(R, t)
        return T @ Ts, T, s
    raise InputError(None, f"unknown alignment {mode!r} (none, se3, sim3, first)")


# ------------------------------------------------------------------------------------- metrics
def error_stats(e: np.ndarray) -> dict:
    """rmse, mean, median, std (population), min, max of an error array (evo's definitions)."""
    e = np.asarray(e, np.float64)
    if len(e) == 0:
        return {k: None for k in ("rmse", "mean", "median", "std", "min", "max")} | {"count": 0}
    return {"rmse": float(np.sqrt(np.mean(e**2))), "mean": float(np.mean(e)), "median": float(np.median(e)),
            "std": float(np.std(e)), "min": float(np.min(e)), "max": float(np.max(e)), "count": int(len(e))}


def rpe_pairs_frames(n: int, delta: int) -> np.ndarray:
    """Consecutive index pairs ``(i, i + delta)`` with ``i`` a multiple of ``delta`` (evo)."""
    ids = np.arange(0, n, delta)
    return np.stack([ids[:-1], ids[1:]], axis=1)


def rpe_pairs_metres(positions: np.ndarray, delta_m: float) -> np.ndarray:
    """Consecutive pairs whose path length reaches ``delta_m`` metres (evo's path filter)."""
    step = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    ids = [0]
    acc = 0.0
    for i, s in enumerate(step, start=1):  # running sum that resets: sequential by nature (N poses)
        acc += float(s)
        if acc >= delta_m:
            ids.append(i)
            acc = 0.0
    ids = np.asarray(ids)
    return np.stack([ids[:-1], ids[1:]], axis=1)


def rpe(T_ref: np.ndarray, T_est: np.ndarray, pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Relative pose errors for index pairs: ``(translation (metres), rotation angle (degrees))``."""
    if len(pairs) == 0:
        return np.zeros(0), np.zeros(0)
    i, j = pairs[:, 0], pairs[:, 1]
    Q = inv_T(T_ref[i]) @ T_ref[j]
    P = inv_T(T_est[i]) @ T_est[j]
    E = inv_T(Q) @ P
    return np.linalg.norm(E[:, :3, 3], axis=1), rotation_angle_deg(E[:, :3, :3])


def camera_yaw_deg(T_model_cam: np.ndarray) -> np.ndarray:
    """Yaw (degrees, (-180, 180]) of camera poses: heading of the optical axis on the model XY plane.

    ``atan2(z_y, z_x)`` of the camera's +z axis in the model frame; when it is within 10 degrees of
    vertical, the heading of the image-up direction (camera -y axis) is used instead.
    """
    R = np.asarray(T_model_cam, np.float64)[..., :3, :3]
    z = R[..., :, 2]
    up = -R[..., :, 1]
    nadir = np.abs(z[..., 2]) > np.cos(np.radians(NADIR_LIMIT_DEG))
    v = np.where(nadir[..., None], up, z)
    return np.degrees(np.arctan2(v[..., 1], v[..., 0]))


def wrap_deg(a: np.ndarray) -> np.ndarray:
    """Wrap angles (degrees) to (-180, 180]."""
    return -((-np.asarray(a, np.float64) + 180.0) % 360.0 - 180.0)


def gap_ranges(missing: np.ndarray, t_ref: np.ndarray) -> list[dict]:
    """Runs of consecutive missing reference indices as dicts (first, last, frames, t_start, t_end)."""
    idx = np.nonzero(missing)[0]
    if len(idx) == 0:
        return []
    brk = np.nonzero(np.diff(idx) > 1)[0]
    starts = np.r_[idx[0], idx[brk + 1]]
    ends = np.r_[idx[brk], idx[-1]]
    return [{"first": int(a), "last": int(b), "frames": int(b - a + 1), "t_start": float(t_ref[a]),
             "t_end": float(t_ref[b])} for a, b in zip(starts, ends)]


def evaluate_trajectories(est_path: str | os.PathLike, ref_path: str | os.PathLike,
                          config: TrajConfig | None = None) -> dict:
    """Compare an estimated trajectory with a reference; returns the summary dict.

    Keys: counts, ``ate`` (metres), ``rotation_error_deg``, ``rpe_frames`` / ``rpe_metres``
    (``translation`` metres, ``rotation_deg``), ``uav_table`` (mean/std of dX dY dZ metres and d-yaw
    degrees), ``gaps``, ``alignment`` (4x4 and scale), and ``series`` (per-pose arrays for plots;
    callers drop it for JSON).
    """
    cfg = config or TrajConfig()
    notes: list[str] = []
    t_est, T_est, rot_e = read_trajectory(est_path, cfg.fmt, cfg.csv_columns, cfg.fps, notes)
    t_ref, T_ref, rot_r = read_trajectory(ref_path, cfg.fmt, cfg.csv_columns, cfg.fps, notes)
    ie, ir = associate(t_est, t_ref, cfg.t_max_diff, cfg.t_offset)
    if len(ie) == 0:
        raise InputError(est_path, f"no timestamps match the reference within {cfg.t_max_diff} s "
                         f"(estimate {t_est[0]:.3f}..{t_est[-1]:.3f} s, reference {t_ref[0]:.3f}..{t_ref[-1]:.3f} s)")
    has_rot = rot_e and rot_r
    Te, Tr = T_est[ie], T_ref[ir]
    if cfg.align == "first" and not has_rot:
        raise InputError(ref_path if rot_e else est_path, "--align first needs orientations (no quaternion columns)")
    if cfg.align in ("se3", "sim3") and len(ie) >= 3:
        # Umeyama needs positions spread in 2 dimensions: name the trajectory that is degenerate
        for path, T in ((est_path, Te), (ref_path, Tr)):
            sv = np.linalg.svd(T[:, :3, 3] - T[:, :3, 3].mean(0), compute_uv=False)
            if sv[1] <= 1e-9 * max(1.0, float(np.abs(T[:, :3, 3]).max())) * np.sqrt(len(T)):
                raise InputError(path, f"the {len(T)} associated positions are identical or on one line: "
                                       f"--align {cfg.align} is not determined (use --align first or none)")
    Ta, T_align, scale = align_estimate(Te, Tr, cfg.align)
    dxyz = Ta[:, :3, 3] - Tr[:, :3, 3]
    ate = np.linalg.norm(dxyz, axis=1)
    out: dict = {
        "estimate": str(est_path), "reference": str(ref_path), "notes": notes,
        "poses_estimate": int(len(t_est)), "poses_reference": int(len(t_ref)), "associated": int(len(ie)),
        "t_max_diff_s": cfg.t_max_diff, "align": cfg.align,
        "alignment": {"T_ref_est": T_align, "scale": scale},
        "ate": error_stats(ate),
    }
    if has_rot:
        out["rotation_error_deg"] = error_stats(rotation_angle_deg(np.swapaxes(Ta[:, :3, :3], -1, -2) @ Tr[:, :3, :3]))
    else:
        out["rotation_error_deg"] = None
    pf = rpe_pairs_frames(len(Ta), max(1, int(cfg.delta)))
    pm = rpe_pairs_metres(Ta[:, :3, 3], cfg.delta_m)
    et, er = rpe(Tr, Ta, pf)
    mt, mr = rpe(Tr, Ta, pm)
    out["rpe_frames"] = {"delta": int(cfg.delta), "translation": error_stats(et),
                         "rotation_deg": error_stats(er) if has_rot else None}
    out["rpe_metres"] = {"delta_m": cfg.delta_m, "translation": error_stats(mt),
                         "rotation_deg": error_stats(mr) if has_rot else None}
    dyaw = wrap_deg(camera_yaw_deg(Ta) - camera_yaw_deg(Tr) - cfg.yaw_offset_deg) if has_rot else None
    table = {}
    for k, name in enumerate(("dX", "dY", "dZ")):
        table[name] = {"mean": float(dxyz[:, k].mean()), "std": float(dxyz[:, k].std()), "unit": "m"}
    table["dyaw"] = ({"mean": float(dyaw.mean()), "std": float(dyaw.std()), "unit": "deg",
                      "yaw_offset_deg": cfg.yaw_offset_deg} if dyaw is not None else None)
    out["uav_table"] = table
    # gaps: reference poses without an estimate within the tolerance (whatever the association side)
    te = t_est + cfg.t_offset
    k = np.clip(np.searchsorted(te, t_ref), 1, max(len(te) - 1, 1))
    near = np.minimum(np.abs(te[k] - t_ref), np.abs(te[k - 1] - t_ref)) if len(te) > 1 else np.abs(te[0] - t_ref)
    missing = near > cfg.t_max_diff
    gaps = gap_ranges(missing, t_ref)
    out["gaps"] = {"missing_reference_poses": int(missing.sum()), "count": len(gaps), "ranges": gaps}
    out["series"] = {"t": t_ref[ir], "xyz_ref": Tr[:, :3, 3], "xyz_est": Ta[:, :3, 3], "dxyz": dxyz,
                     "dyaw": dyaw, "t_ref_all": t_ref, "xyz_ref_all": T_ref[:, :3, 3]}
    return out


def report_rows(s: dict) -> list[list[str]]:
    """The main numbers as (metric, value) rows for the console table."""
    def f(v, nd=4):
        return "-" if v is None else f"{v:.{nd}f}"

    rows = [["associated poses", f"{s['associated']} (est {s['poses_estimate']}, ref {s['poses_reference']})"],
            ["alignment", f"{s['align']}" + (f" (scale {s['alignment']['scale']:.6f})" if s["align"] == "sim3" else "")]]
    a = s["ate"]
    rows.append(["ATE [m] rmse / mean / median / std / min / max",
                 " / ".join(f(a[k]) for k in ("rmse", "mean", "median", "std", "min", "max"))])
    if s["rotation_error_deg"]:
        r = s["rotation_error_deg"]
        rows.append(["rotation error [deg] rmse / mean / max", " / ".join(f(r[k], 3) for k in ("rmse", "mean", "max"))])
    for key, lab in (("rpe_frames", f"RPE {s['rpe_frames']['delta']} frame(s)"),
                     ("rpe_metres", f"RPE {s['rpe_metres']['delta_m']:g} m")):
        tr = s[key]["translation"]
        rr = s[key]["rotation_deg"]
        rows.append([f"{lab} [m] rmse / mean", f"{f(tr['rmse'])} / {f(tr['mean'])} ({tr['count']} pairs)"])
        if rr:
            rows.append([f"{lab} [deg] rmse / mean", f"{f(rr['rmse'], 3)} / {f(rr['mean'], 3)}"])
    g = s["gaps"]
    rows.append(["gaps (reference poses without estimate)",
                 f"{g['missing_reference_poses']} poses in {g['count']} range(s)"])
    return rows


def uav_rows(s: dict) -> list[list[str]]:
    """UAV-paper table rows: quantity, mean, std."""
    rows = []
    for k, lab in (("dX", "dX [m]"), ("dY", "dY [m]"), ("dZ", "dZ [m]"), ("dyaw", "d-yaw [deg]")):
        v = s["uav_table"][k]
        rows.append([lab, "-" if v is None else f"{v['mean']:.4f}", "-" if v is None else f"{v['std']:.4f}"])
    return rows
