"""Small valid inputs for every ``mst`` command (fixed seed), from which tests/test_bad_input.py derives
bad ones: a 0.4 x 0.3 x 0.2 m box model, a 320x240 camera (a pose there is pinned within the error budget of a first frame), a pose, clicks, frames, a trajectory,
depth frames, a cloud. Everything is tiny so that a command runs in milliseconds in-process."""

from __future__ import annotations

import contextlib
import io
import sys
from pathlib import Path

import numpy as np

from mst.core.camera import Camera, write_camera
from mst.core.poses import inv_T, look_at
from mst.core.trajectory import format_tum, write_pose_file

CAM = Camera(400.0, 400.0, 159.5, 119.5, 320, 240)
BOX_V = np.array([[x, y, z] for z in (0.0, 0.2) for y in (0.0, 0.3) for x in (0.0, 0.4)], float)
# quads, outward normals (counter-clockwise seen from outside)
BOX_F = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
CENTRE = BOX_V.mean(0)


def T_model_cam_at(k: int) -> np.ndarray:
    """Camera pose k of a short arc around the box (metres, model frame)."""
    a = np.radians(-40.0 + 2.0 * k)
    eye = CENTRE + 1.4 * np.array([np.cos(a), np.sin(a), 0.6])
    return look_at(eye, CENTRE)


def project(T_cam_model: np.ndarray, X: np.ndarray) -> np.ndarray:
    Xc = X @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
    return Xc[:, :2] / Xc[:, 2:3] * [CAM.fx, CAM.fy] + [CAM.cx, CAM.cy]


def render_frame(T_cam_model: np.ndarray) -> np.ndarray:
    """BGR 320x240 picture of the box (faces filled far to near, grey per face) on a dark background."""
    import cv2

    img = np.full((CAM.height, CAM.width, 3), 40, np.uint8)
    Xc = BOX_V @ T_cam_model[:3, :3].T + T_cam_model[:3, 3]
    order = sorted(range(len(BOX_F)), key=lambda f: -Xc[BOX_F[f], 2].mean())
    uv = project(T_cam_model, BOX_V)
    for f in order:
        pts = np.round(uv[BOX_F[f]] * 16).astype(np.int32)
        cv2.fillPoly(img, [pts], (90 + 30 * f,) * 3, cv2.LINE_AA, shift=4)
    return img


def build(d: Path) -> dict[str, Path]:
    """Write the valid fixture set into folder ``d``; returns name -> path."""
    import cv2

    rng = np.random.default_rng(9)
    d.mkdir(parents=True, exist_ok=True)
    f: dict[str, Path] = {}
    f["model"] = d / "box.obj"
    f["model"].write_text("".join(f"v {a:.6f} {b:.6f} {c:.6f}\n" for a, b, c in BOX_V)
                          + "".join("f " + " ".join(str(i + 1) for i in q) + "\n" for q in BOX_F))
    f["camera"] = d / "cam.json"
    write_camera(f["camera"], CAM)
    T0 = inv_T(T_model_cam_at(0))
    f["pose"] = d / "pose0.txt"
    write_pose_file(f["pose"], T0)
    uv = project(T0, BOX_V)
    f["clicks"] = d / "clicks.txt"
    f["clicks"].write_text("".join(" ".join(f"{v:.4f}" for v in (*X, *p)) + "\n" for X, p in zip(BOX_V, uv)))
    f["uv"] = d / "uv.clicks"
    f["uv"].write_text("".join(f"{u:.3f} {v:.3f}\n" for u, v in uv[:6]))
    f["points"] = d / "box.init"
    f["points"].write_text("6\n" + "".join(f"{a} {b} {c}\n" for a, b, c in BOX_V[:6]))
    f["frames"] = d / "frames"
    f["frames"].mkdir()
    n = 3
    for k in range(n):
        cv2.imwrite(str(f["frames"] / f"{k:06d}.png"), render_frame(inv_T(T_model_cam_at(k))))
    f["image"] = f["frames"] / "000000.png"
    Ts = np.stack([T_model_cam_at(k) for k in range(n)])
    f["traj"] = d / "traj.txt"
    f["traj"].write_text(format_tum(np.arange(n, dtype=float), Ts))
    Tg = np.stack([T_model_cam_at(k) for k in range(6)])
    Tg[:, :3, 3] += rng.normal(0, 0.002, (6, 3))
    f["gt"] = d / "gt.txt"
    f["gt"].write_text(format_tum(np.arange(6, dtype=float), Tg))
    f["depth"] = d / "depth"
    f["depth"].mkdir()
    for k in range(n):
        np.save(f["depth"] / f"{k:06d}.npy", np.full((CAM.height, CAM.width), 1.5, np.float32)
                + rng.normal(0, 0.001, (CAM.height, CAM.width)).astype(np.float32))
    f["extrinsic"] = d / "depth_M_color.txt"
    f["extrinsic"].write_text("1 0 0 0.01\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    # cloud: points on the box surface (faces z = 0.2 and x = 0.4), 1 mm noise
    m = 300
    top = np.column_stack([rng.uniform(0, 0.4, m), rng.uniform(0, 0.3, m), np.full(m, 0.2)])
    side = np.column_stack([np.full(m, 0.4), rng.uniform(0, 0.3, m), rng.uniform(0, 0.2, m)])
    P = np.vstack([top, side]) + rng.normal(0, 0.001, (2 * m, 3))
    f["cloud"] = d / "cloud.ply"
    f["cloud"].write_text("ply\nformat ascii 1.0\n" f"element vertex {len(P)}\n"
                          "property double x\nproperty double y\nproperty double z\nend_header\n"
                          + "".join(f"{a:.6f} {b:.6f} {c:.6f}\n" for a, b, c in P))
    f["xyz"] = d / "cloud.xyz"
    f["xyz"].write_text("".join(f"{a:.6f} {b:.6f} {c:.6f}\n" for a, b, c in P))
    return f


def run_cli(args: list) -> tuple[int, str, str]:
    """Run ``mst ARGS`` in-process (``mst.cli.main.main``); returns (exit code, stdout, stderr)."""
    from mst.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    code = None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([str(a) for a in args])
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else (0 if e.code is None else 1)
    return code, out.getvalue(), err.getvalue()


if __name__ == "__main__":  # build a set for manual trials: python tests/bad_input_fixtures.py DIR
    print(build(Path(sys.argv[1])))
