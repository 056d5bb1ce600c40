"""``mst init``: the first camera pose from clicked model points (PnP + robust refinement).

Inputs: a clicks file with ``X Y Z u v`` per line (model metres, pixels), or ``u v`` per line with a
ViSP ``.init`` points file (first line the count, then ``X Y Z`` per line), in the same order.
Pose: ``cv2.solvePnP`` (SQPnP, EPnP and iterative; the lowest error wins) then a robust
Levenberg-Marquardt refinement (Huber weights at 2 px) of the reprojection error. Per-point
residuals (pixels) are returned; large residuals are diagnosed: a swap of two clicks that fits
is named, otherwise the camera (focal length / principal point) is suspected.

``pose_from_gps``: an approximate pose from a position and yaw/pitch/roll in the model frame (a
UAV's GPS + AHRS) and a fixed camera-mount rotation; conventions in its docstring.
"""

from __future__ import annotations

import itertools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mst import InputError
from mst.core.config import Config, param, section
from mst.core.poses import transform_points
from mst.pipeline.autoinit import AutoInitConfig

#: largest accepted model coordinate (metres) and pixel coordinate of a click: beyond these the
#: values are corrupt (PnP would overflow or return a camera 1e12 m away)
MAX_COORD_M = 1e9
MAX_PIXEL = 1e6
#: clicks closer than this (px) are one position; the image points must also spread at least this
#: far off their best-fit line (RMS), or the pose is not determined (a few px of click error)
MIN_SPREAD_PX = 1.0


@dataclass
class InitConfig(Config):
    """Settings of ``mst init``: the residual bound of a clicked pose, the camera mount of a pose
    guess (a GPS/AHRS position and attitude) and the automatic search around a nav-log guess."""

    max_residual_px: float = param(4.0, min=0, min_open=True,
                                   help="RMS reprojection error above which init fails with a diagnosis, px")
    mount_ypr_deg: tuple[float, float, float] = param((0.0, 0.0, 0.0), help="camera-mount rotation relative to the "
                                                                         "vehicle body (yaw, pitch, roll), deg")
    mount_offset_m: tuple[float, float, float] = param((0.0, 0.0, 0.0), help="camera lever arm in the body frame, m")
    auto: AutoInitConfig = section(AutoInitConfig)


def _read_numbers(path: Path, what: str) -> list[list[float]]:
    from mst import read_text

    rows = []
    for ln, line in enumerate(read_text(path, what).splitlines(), 1):
        s = line.split("#", 1)[0].replace(",", " ").strip()
        if not s:
            continue
        try:
            rows.append([float(x) for x in s.split()])
        except ValueError:
            raise InputError(path, f"line {ln}: not a number: {s[:60]!r}") from None
    return rows


def check_spread(p, a: np.ndarray, what: str, tol: float) -> None:
    """Refuse (N, d) points that PnP cannot use: fewer than 4 distinct, or all on one line.

    ``tol`` is the distance below which two points are one (metres for model points, px for
    clicks); the RMS distance of the points from their best-fit line must exceed it too.
    Raises :class:`mst.InputError` naming file ``p``.
    """
    a = np.asarray(a, np.float64)
    distinct = len(np.unique(np.round(a / tol), axis=0))
    if distinct < min(4, len(a)):
        raise InputError(p, f"the {len(a)} {what} are only {distinct} distinct position(s): need 4 different ones")
    c = a - a.mean(0)
    sv = np.linalg.svd(c, compute_uv=False)
    if len(sv) < 2 or sv[1] / np.sqrt(len(a)) < tol:
        raise InputError(p, f"the {what} lie on one line: the pose is not determined (spread them out)")


def read_init_points(path: str | os.PathLike) -> np.ndarray:
    """ViSP ``.init`` file: count, then ``X Y Z`` lines -> (N,3) metres (model frame)."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "points file does not exist")
    rows = _read_numbers(p, "points file")
    if not rows or len(rows[0]) != 1:
        raise InputError(p, "expected the point count on the first line (ViSP .init format)")
    if not (np.isfinite(rows[0][0]) and rows[0][0] == int(rows[0][0]) and 1 <= rows[0][0] <= 1e6):
        raise InputError(p, f"the point count {rows[0][0]:g} on the first line is not a positive integer")
    n = int(rows[0][0])
    pts = rows[1:]
    if len(pts) != n or any(len(r) != 3 for r in pts):
        raise InputError(p, f"header says {n} points but {len(pts)} 'X Y Z' lines follow"
                         if len(pts) != n else "every point line needs 3 numbers 'X Y Z'")
    a = np.array(pts, float).reshape(-1, 3)
    if not np.isfinite(a).all():
        raise InputError(p, "points hold NaN or infinite values")
    if np.abs(a).max() > MAX_COORD_M:
        raise InputError(p, f"a point coordinate is beyond {MAX_COORD_M:g} m (corrupt value?)")
    return a


def read_clicks(path: str | os.PathLike, points_path: str | os.PathLike | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Return ``(X_model (N,3) metres, uv (N,2) px)`` from a clicks file (+ optional .init file)."""
    p = Path(path)
    if not p.exists():
        raise InputError(p, "clicks file does not exist")
    rows = _read_numbers(p, "clicks file")
    if not rows:
        raise InputError(p, "no clicks in the file")
    widths = {len(r) for r in rows}
    if points_path is not None:
        if widths != {2}:
            raise InputError(p, "with a points file, every click line needs 2 numbers 'u v'")
        X = read_init_points(points_path)
        uv = np.array(rows, float)
        if len(X) != len(uv):
            raise InputError(p, f"{len(uv)} clicks but {len(X)} points in {points_path}: they must pair up in order")
    else:
        if widths == {2}:
            raise InputError(p, "clicks are 'u v' only: their model points come from a ViSP .init points file")
        if widths != {5}:
            raise InputError(p, "every click line needs 5 numbers 'X Y Z u v' (or 'u v' with a points file)")
        a = np.array(rows, float)
        X, uv = a[:, :3], a[:, 3:]
    x_file = p if points_path is None else Path(points_path)
    if not (np.isfinite(X).all() and np.isfinite(uv).all()):
        raise InputError(p, "clicks hold NaN or infinite values")
    if len(uv) < 4:
        raise InputError(p, f"{len(uv)} clicks, need at least 4")
    if np.abs(X).max() > MAX_COORD_M:
        raise InputError(x_file, f"a model point coordinate is beyond {MAX_COORD_M:g} m (corrupt value?)")
    if np.abs(uv).max() > MAX_PIXEL:
        raise InputError(p, f"a click is beyond {MAX_PIXEL:g} px (corrupt value?)")
    # degenerate geometry: blamed on the file that holds it (the model points may be the .init file)
    extent = float(np.abs(X - X.mean(0)).max())
    check_spread(x_file, X, "model points", max(1e-9, 1e-6 * extent))
    check_spread(p, uv, "clicks", MIN_SPREAD_PX)
    return X, uv


def project(T_cam_model: np.ndarray, K: np.ndarray, X: np.ndarray) -> np.ndarray:
    """(N,3) model points -> (N,2) pixels (no distortion): :meth:`Camera.project` of the pinhole ``K``."""
    return _pinhole(K).project(transform_points(T_cam_model, X))


def _pinhole(K: np.ndarray):
    from mst.core.camera import Camera

    return Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2])


def _T_from_rt(rvec, tvec) -> np.ndarray:
    import cv2

    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.asarray(rvec, float).reshape(3, 1))[0]
    T[:3, 3] = np.asarray(tvec, float).ravel()
    return T


def refine_pose(T: np.ndarray, K: np.ndarray, X: np.ndarray, uv: np.ndarray, iters: int = 30, huber_px: float = 2.0) -> np.ndarray:
    """Robust LM (Huber) refinement of the reprojection error; perturbation ``se3_exp(xi) @ T``."""
    from mst.core.poses import se3_exp
    from mst.pipeline.tracking.vvs import _point_jacobian

    fx, fy = K[0, 0], K[1, 1]
    mu = 1e-3

    def res(Tc):
        return (project(Tc, K, X) - uv).ravel()

    for _ in range(iters):
        Xc = X @ T[:3, :3].T + T[:3, 3]
        iz = 1.0 / Xc[:, 2]
        J = _point_jacobian(Xc[:, 0] * iz, Xc[:, 1] * iz, iz, fx, fy).reshape(-1, 6)
        r = res(T)
        a = np.abs(r)
        w = np.where(a <= huber_px, 1.0, huber_px / np.maximum(a, 1e-12))
        H = J.T @ (w[:, None] * J)
        g = J.T @ (w * r)
        cost = np.sum(w * r * r)
        improved = False
        for _ in range(6):
            xi = -np.linalg.solve(H + mu * np.diag(np.diag(H) + 1e-12), g)
            Tn = se3_exp(xi) @ T
            rn = res(Tn)
            if np.sum(w * rn * rn) <= cost:
                T, mu, improved = Tn, mu * 0.1, True
                break
            mu *= 10
        if not improved or np.abs(xi).max() < 1e-12:
            break
    return T


def solve_pnp(X: np.ndarray, uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """Best of SQPnP / EPnP / iterative PnP (lowest RMS), refined robustly. Returns ``T_cam_model``."""
    import cv2

    dist = np.zeros(4) if dist is None or not len(dist) else np.asarray(dist, float)
    best, best_err = None, np.inf
    Xf, uf = X.astype(np.float64).reshape(-1, 1, 3), uv.astype(np.float64).reshape(-1, 1, 2)
    flags = [cv2.SOLVEPNP_SQPNP, cv2.SOLVEPNP_EPNP, cv2.SOLVEPNP_ITERATIVE]
    if len(X) == 4:
        flags.append(cv2.SOLVEPNP_AP3P)
    for flag in flags:
        try:
            ok, rvec, tvec = cv2.solvePnP(Xf, uf, K, dist, flags=flag)
        except cv2.error:
            continue
        if not ok:
            continue
        T = _T_from_rt(rvec, tvec)
        Xc = X @ T[:3, :3].T + T[:3, 3]
        if (Xc[:, 2] <= 0).any():
            continue
        if not dist.any():
            T = refine_pose(T, K, X, uv)
        e = np.sqrt(np.mean(np.sum((project(T, K, X) - uv) ** 2, 1)))
        if e < best_err:
            best, best_err = T, e
    if best is None:
        raise ValueError("PnP found no pose with the points in front of the camera")
    return best


@dataclass
class InitResult:
    """T_cam_model (4,4); residual_px (N,) per click; rms_px; diagnosis ('' when fine)."""

    T_cam_model: np.ndarray
    residual_px: np.ndarray
    rms_px: float
    diagnosis: str


def diagnose(X: np.ndarray, uv: np.ndarray, K: np.ndarray, residual_px: np.ndarray, max_px: float) -> str:
    """Explain large residuals: a swap of two clicks that fits, else a suspect camera."""
    n = len(X)
    base = float(np.sqrt(np.mean(residual_px**2)))
    best = None
    worst = np.argsort(-residual_px)[: min(n, 6)]
    for i, j in itertools.combinations(sorted(set(worst.tolist()) | set(range(min(n, 6)))), 2):
        uv2 = uv.copy()
        uv2[[i, j]] = uv2[[j, i]]
        try:
            T = solve_pnp(X, uv2, K)
        except ValueError:
            continue
        r = np.linalg.norm(project(T, K, X) - uv2, axis=1)
        rms = float(np.sqrt(np.mean(r**2)))
        if best is None or rms < best[0]:
            best = (rms, i, j)
    if best is not None and best[0] <= max_px and best[0] < 0.25 * base:
        return (f"clicks {best[1] + 1} and {best[2] + 1} look swapped: swapping them gives {best[0]:.2f} px RMS "
                f"instead of {base:.2f} px")
    return (f"reprojection RMS {base:.1f} px > {max_px:g} px and no swap of two clicks fits: the camera "
            f"intrinsics (focal length fx={K[0, 0]:.1f}, principal point {K[0, 2]:.1f},{K[1, 2]:.1f}) are suspect, "
            "or the clicks/points do not correspond")


def init_from_clicks(X: np.ndarray, uv: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None,
                     max_rms_px: float = 4.0) -> InitResult:
    """PnP + refinement; ``diagnosis`` is set when the RMS residual exceeds ``max_rms_px``.

    With distortion coefficients ``dist`` (OpenCV order) the clicks are undistorted first; the
    residuals are then in undistorted pixels.
    """
    if len(X) < 4:
        raise ValueError(f"{len(X)} points, need at least 4")
    if np.linalg.matrix_rank(X - X.mean(0), tol=1e-9 * max(1.0, np.abs(X).max())) < 2:
        raise ValueError("the model points are collinear: PnP needs them spread out")
    if dist is not None and len(dist) and np.any(dist != 0):
        # undistort the clicks once: PnP, refinement and diagnosis then use the pinhole model
        import cv2

        d = np.zeros(5)
        d[: min(5, len(dist))] = np.asarray(dist, float)[:5]
        uv = cv2.undistortPoints(uv.reshape(-1, 1, 2).astype(np.float64), K, d, P=K).reshape(-1, 2)
    T = solve_pnp(X, uv, K)
    r = np.linalg.norm(project(T, K, X) - uv, axis=1)
    rms = float(np.sqrt(np.mean(r**2)))
    diag = diagnose(X, uv, K, r, max_rms_px) if rms > max_rms_px else ""
    return InitResult(T, r, rms, diag)


def pose_from_gps(position_m: np.ndarray, yaw_deg: float, pitch_deg: float, roll_deg: float,
                  mount_ypr_deg: tuple[float, float, float] = (0.0, 0.0, 0.0),
                  mount_offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """An approximate ``T_cam_model`` from a vehicle position and attitude in the model frame.

    Conventions: the model frame is x east, y north, z up (ENU, metres). The vehicle body frame is
    x forward, y left, z up; its attitude is ``R_model_body = Rz(yaw) @ Ry(-pitch) @ Rx(roll)``:
    yaw counter-clockwise from the model x axis (east) about z, pitch positive nose *up*, roll
    positive right wing *down* (so yaw=0, pitch=0, roll=0 looks along +x, level). The camera
    mount is a fixed rotation of the camera relative to the body, given as yaw/pitch/roll with the
    same convention (e.g. ``(0, -90, 0)`` for a nadir camera) plus a lever arm ``mount_offset_m``
    in the body frame. The camera looks along the rotated body x axis; its image x is the body's
    -y (right) and image y the body's -z (down).
    """
    from scipy.spatial.transform import Rotation as Rot

    def ypr(y, p, r):
        return Rot.from_euler("ZYX", [y, -p, r], degrees=True).as_matrix()

    R_model_body = ypr(yaw_deg, pitch_deg, roll_deg)
    R_body_mount = ypr(*mount_ypr_deg)
    # camera axes (x right, y down, z forward) in the mount frame (x fwd, y left, z up)
    R_mount_cam = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    R_model_cam = R_model_body @ R_body_mount @ R_mount_cam
    t_model_cam = np.asarray(position_m, float) + R_model_body @ np.asarray(mount_offset_m, float)
    T_model_cam = np.eye(4)
    T_model_cam[:3, :3] = R_model_cam
    T_model_cam[:3, 3] = t_model_cam
    from mst.core.poses import inv_T

    return inv_T(T_model_cam)


def draw_model(bgr: np.ndarray, model, T_cam_model: np.ndarray, K: np.ndarray, near: float = 1e-3,
               color=(0, 255, 0), points: np.ndarray | None = None, numbers: bool = False, clicks: np.ndarray | None = None,
               model_path=None) -> np.ndarray:
    """Draw the model's edges (clipped at the near plane) and optional numbered points. With ``model_path``, a model
    that ``mst track --edges auto`` follows by render-based edges (a curved or many-faced mesh, a ``.cao`` with
    cylinders) is drawn as the contour points of its render at the pose instead
    (:func:`mst.pipeline.tracking.render_edges.contour_uv`)."""
    import cv2

    from mst.pipeline.tracking.visibility import _clip_near_far

    out = bgr.copy()
    uv = None
    if model_path is not None:
        from mst.core.camera import Camera
        from mst.pipeline.tracking.render_edges import contour_uv

        H, W = out.shape[:2]
        uv = contour_uv(model, model_path, T_cam_model, Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], W, H))
    if uv is not None:
        for p in np.rint(uv[np.isfinite(uv).all(1)]).astype(np.int64):
            cv2.circle(out, (int(p[0]), int(p[1])), 1, color, -1, cv2.LINE_AA)
    else:
        E = model.edges()
        V = np.asarray(model.vertices)
        A = transform_points(T_cam_model, V[E[:, 0]])
        B = transform_points(T_cam_model, V[E[:, 1]])
        A, B, keep, _, _ = _clip_near_far(A, B, near, 1e12)
        A, B = A[keep], B[keep]
        pa, pb = _pinhole(K).project(A), _pinhole(K).project(B)
        lim = 1e5
        for a, b in zip(np.clip(pa, -lim, lim), np.clip(pb, -lim, lim)):
            cv2.line(out, (int(a[0]), int(a[1])), (int(b[0]), int(b[1])), color, 1, cv2.LINE_AA)
    if points is not None:
        pp = project(T_cam_model, K, points)
        for i, p in enumerate(pp):
            c = (int(round(p[0])), int(round(p[1])))
            cv2.circle(out, c, 4, (0, 0, 255), -1)
            if numbers:
                cv2.putText(out, str(i + 1), (c[0] + 6, c[1] - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (0, 0, 255), 2, cv2.LINE_AA)
    if clicks is not None:
        for p in clicks:
            cv2.drawMarker(out, (int(round(p[0])), int(round(p[1]))), (255, 0, 255), cv2.MARKER_CROSS, 10, 1)
    return out


def _default_view(model, K: np.ndarray, width: int, height: int) -> np.ndarray:
    """A look-at ``T_cam_model`` showing the whole model from an oblique direction."""
    V = np.asarray(model.vertices)
    c = 0.5 * (V.min(0) + V.max(0))
    r = max(float(np.linalg.norm(V - c, axis=1).max()), 1e-6)
    fov = 2 * np.arctan(0.5 * min(width / K[0, 0], height / K[1, 1]))
    d = np.array([0.6, -0.8, 0.6])
    d /= np.linalg.norm(d)
    eye = c + d * (1.3 * r / np.sin(fov / 2))
    z = (c - eye) / np.linalg.norm(c - eye)
    up = np.array([0.0, 0.0, 1.0])
    x = np.cross(z, -up)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z])  # rows: camera axes in the model frame
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = -R @ eye
    return T


def _read_image(path) -> np.ndarray:
    from mst.pipeline.frames import open_frames

    src = open_frames(path, "0:1")
    for _, _, bgr in src:
        return bgr
    raise InputError(path, "no frame could be read")


def _write_points_picture(out, model, cam, img, clicks_path, points_path, summary: dict, model_path=None) -> dict:
    """``--show-points``: the model with its numbered points, drawn with the clicked pose on the image
    (when clicks and the image are given) or from a default view on white, written to ``out``."""
    import cv2

    from mst import atomic_output

    K = cam.K
    pts = read_init_points(points_path) if points_path else None
    if pts is None and clicks_path:
        pts = read_clicks(clicks_path)[0]
    if pts is None:
        raise InputError(None, "showing the points needs a points file (or clicks with 'X Y Z u v')")
    T = None
    if clicks_path and img is not None:
        X, uv = read_clicks(clicks_path, points_path)
        T = solve_pnp(X, uv, K, cam.dist)
    if T is None:
        T = _default_view(model, K, cam.width, cam.height)
        canvas = np.full((cam.height, cam.width, 3), 255, np.uint8)
    else:
        canvas = img
    pic = draw_model(canvas, model, T, K, color=(200, 80, 0), points=pts, numbers=True, model_path=model_path)
    with atomic_output(out) as tmp:
        if not cv2.imwrite(str(tmp), pic):
            raise InputError(out, "could not write the picture (use .png)")
    summary.update({"picture": str(out), "points": pts})
    return summary


def run_init(model_path, camera_path, out, *, clicks_path=None, points_path=None, from_pose=None,
             image_path=None, overlay_path=None, show_points: bool = False, cfg: InitConfig | None = None) -> dict:
    """The ``mst init`` stage: write the pose file ``out`` (or, with ``show_points``, a PNG).

    One source of the pose: ``clicks_path`` (with ``points_path`` for 'u v' clicks) or
    ``from_pose`` (x y z yaw pitch roll; the mount from ``cfg``). Returns a summary dict (pose as
    ``T_cam_model``, per-click residuals in px, RMS, the effective ``config``). Raises
    :class:`mst.InputError` for bad input or a failed, diagnosed initialisation.
    """
    cfg = cfg or InitConfig()
    import cv2

    from mst import atomic_outputs
    from mst.core.camera import read_camera
    from mst.core.trajectory import write_pose_file
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.tracking import check_pose_in_view

    if overlay_path is not None and image_path is None:
        raise InputError(overlay_path, "an overlay needs the image to draw on")
    model = load_tracking_model(model_path)
    cam = read_camera(camera_path)
    img = None
    if image_path is not None:
        img = _read_image(image_path)
        h, w = img.shape[:2]
        if cam.width and cam.height and (cam.width, cam.height) != (w, h):
            raise InputError(camera_path, f"camera is for {cam.width}x{cam.height} images but {image_path} is {w}x{h}")
        cam = cam.with_size(w, h)
    if not cam.width:
        cam = cam.with_size(int(round(2 * cam.cx + 1)), int(round(2 * cam.cy + 1)))
    K = cam.K
    summary: dict = {"camera": cam.to_dict(), "residual_px": None, "config": cfg.to_dict()}

    if show_points:
        return _write_points_picture(out, model, cam, img, clicks_path, points_path, summary, model_path)

    if from_pose is not None:
        if clicks_path:
            raise InputError(clicks_path, "give either clicks or a pose guess, not both")
        T = pose_from_gps(np.array(from_pose[:3]), *from_pose[3:], mount_ypr_deg=tuple(cfg.mount_ypr_deg),
                          mount_offset_m=tuple(cfg.mount_offset_m))
        check_pose_in_view(model, T, cam, "--from-pose")  # the option is wrong, not the output file
        summary["source"] = "from-pose"
    else:
        if not clicks_path:
            raise InputError(None, "no pose source: give clicks (with a points file for 'u v' clicks) or a pose guess")
        X, uv = read_clicks(clicks_path, points_path)
        if img is not None:
            outside = (uv[:, 0] < 0) | (uv[:, 1] < 0) | (uv[:, 0] > cam.width) | (uv[:, 1] > cam.height)
            if outside.any():
                raise InputError(clicks_path, f"click(s) {', '.join(str(i + 1) for i in np.flatnonzero(outside))} lie outside the "
                                              f"{cam.width}x{cam.height} image")
        try:
            res = init_from_clicks(X, uv, K, cam.dist, cfg.max_residual_px)
        except ValueError as e:
            raise InputError(clicks_path, str(e)) from None
        summary.update({"source": "clicks", "uv": uv, "X_model": X, "residual_px": res.residual_px, "rms_px": res.rms_px})
        if res.diagnosis:
            per = ", ".join(f"#{i + 1} {r:.1f}" for i, r in enumerate(res.residual_px))
            raise InputError(clicks_path, f"{res.diagnosis} (residuals px: {per})")
        T = res.T_cam_model
    summary["T_cam_model"] = T
    with atomic_outputs(out, overlay_path) as (tmp, tmp_ov):
        write_pose_file(tmp, T)
        if tmp_ov is not None:
            pic = draw_model(img, model, T, K, points=summary.get("X_model"), clicks=summary.get("uv"), model_path=model_path)
            if not cv2.imwrite(str(tmp_ov), pic):
                raise InputError(overlay_path, "could not write the overlay (use .png)")
    return summary
