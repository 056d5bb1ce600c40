"""Synth outputs: the sequence folder (written in a temporary folder, moved into place at once),
the per-frame files, the metadata files (gt.txt, camera.json, clicks.txt, model.obj, scene.ply,
frames.csv, scene.json) and the scene mesh's PLY writer."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from mst import InputError, MstError, __version__
from mst.core.camera import write_camera
from mst.core.ply import write_ply
from mst.core.trajectory import format_tum
from mst.pipeline.synth.config import LATER_FIELDS

#: the scene.json layout this mst writes and reads (a file of another version is refused, never guessed)
SCENE_VERSION = 1


def write_ply_mesh(path: Path, V: np.ndarray, F: np.ndarray, labels: np.ndarray) -> None:
    """Binary little-endian PLY (:func:`mst.core.ply.write_ply`): double vertices, int triangles,
    uchar face ``label``."""
    V = np.asarray(V, np.float64)
    write_ply(path, {"x": V[:, 0], "y": V[:, 1], "z": V[:, 2]}, F,
              face_properties={"label": np.asarray(labels, np.uint8)},
              comments=["mst synth scene: labels 0 model 1 floor 2 wall 3 ceiling"])


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


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
            raise InputError(out_dir, "output folder is not empty (allow overwriting to replace its sequence files)")
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


class H264Writer:
    """An H.264 (libx264, yuv420p) mp4 writer with the ``cv2.VideoWriter`` calls synth uses.

    OpenCV's wheels carry no H.264 encoder (``avc1`` fails to open), so the frames go to the static
    ffmpeg of ``imageio-ffmpeg``. ``crf`` is x264's constant rate factor (18: visually lossless,
    the artefacts of a real drone video's 23-28 are stronger); one encoder thread keeps the bytes the
    same from run to run.
    """

    def __init__(self, path: Path, fps: float, size_px: tuple[int, int], crf: int = 23):
        try:
            import imageio_ffmpeg
        except ImportError:  # pragma: no cover - a dependency in pyproject
            raise MstError("H.264 video needs the imageio-ffmpeg package (pip install imageio-ffmpeg)") from None
        w, h = size_px
        if w % 2 or h % 2:
            raise MstError(f"H.264 (yuv420p) needs an even frame size, not {w}x{h}")
        self._gen = imageio_ffmpeg.write_frames(
            str(path), (w, h), fps=fps, codec="libx264", pix_fmt_in="bgr24", pix_fmt_out="yuv420p",
            macro_block_size=1, ffmpeg_log_level="error",
            output_params=["-crf", str(int(crf)), "-preset", "medium", "-threads", "1", "-bf", "0"])
        self._gen.send(None)

    def isOpened(self) -> bool:  # noqa: N802 - the cv2.VideoWriter name
        return True

    def write(self, bgr: np.ndarray) -> None:
        self._gen.send(np.ascontiguousarray(bgr, np.uint8))

    def release(self) -> None:
        self._gen.close()


def write_frame(tmp: Path, frame, T_cam_model: np.ndarray, writer, with_depth: bool) -> None:
    """One rendered frame: rgb/%06d.png (+ the video), depth/%06d.png (mm) and .npy (m), cMo/%06d.txt."""
    import cv2

    from mst.pipeline import render_kernels as rk

    k = frame.index
    cv2.imwrite(str(tmp / "rgb" / f"{k:06d}.png"), frame.bgr)
    if writer is not None:
        writer.write(frame.bgr)
    if with_depth:
        depth = frame.depth
        mm = np.empty(depth.shape, np.uint16)
        rk.depth_to_mm(np.ascontiguousarray(depth, np.float32), mm)
        cv2.imwrite(str(tmp / "depth" / f"{k:06d}.png"), mm)
        np.save(tmp / "depth" / f"{k:06d}.npy", depth.astype(np.float32))
    (tmp / "cMo" / f"{k:06d}.txt").write_text(
        "".join(" ".join(f"{v:.15g}" for v in row) + "\n" for row in T_cam_model))


def write_metadata(tmp: Path, plan, cfg, scenario: str, V: np.ndarray, F: np.ndarray, rows: list,
                   model_source: str) -> None:
    """gt.txt, camera.json, clicks.txt, model.obj, scene.ply, frames.csv and scene.json of a sequence."""
    from mst.meshtools.formats import save_triangles

    fps = float(cfg.fps)
    frames = len(plan.T_model_cam)
    (tmp / "gt.txt").write_text(
        "# mst synth ground truth: camera pose in the model frame (TUM: t tx ty tz qx qy qz qw), t = frame / fps\n"
        + format_tum(np.arange(frames) / fps, plan.T_model_cam))
    write_camera(tmp / "camera.json", plan.cam)
    (tmp / "clicks.txt").write_text(
        "# mst synth clicks for frame 0: X Y Z (model frame, metres) u v (pixels)"
        + (f", pixel noise sigma {cfg.click_noise:g}" if cfg.click_noise > 0 else "") + "\n"
        + "".join(f"{X[0]:.9f} {X[1]:.9f} {X[2]:.9f} {uv[0]:.4f} {uv[1]:.4f}\n"
                  for X, uv in zip(plan.click_X, plan.click_uv)))
    save_triangles(tmp / "model.obj", V, F)  # shortest round-trip text: float64 vertices exact
    V_all, F_all, mat_all = plan.mesh
    write_ply_mesh(tmp / "scene.ply", V_all, F_all, mat_all)
    (tmp / "frames.csv").write_text("frame,time,model_px,edge_px\n"
                                    + "".join(f"{k},{t:.6f},{m},{e}\n" for k, t, m, e in rows))
    spec = {
        "format": "mst-synth-scene", "version": SCENE_VERSION, "mst_version": __version__,
        "scenario": scenario, "seed": int(cfg.seed),
        "config": {k: v for k, v in cfg.to_dict().items() if k not in LATER_FIELDS or v != LATER_FIELDS[k]},
        "model": {"source": str(model_source), "file": "model.obj",
                  "sha256": _sha256(tmp / "model.obj"), "vertices": len(V), "triangles": len(F)},
        "camera": plan.cam.to_dict(), "resolved": plan.scene.params,
    }
    (tmp / "scene.json").write_text(json.dumps(spec, indent=2) + "\n")
