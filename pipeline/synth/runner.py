"""The ``mst synth`` runner: check the scenario, read the model, plan the sequence, render and write
its frames into a temporary folder, write the metadata, move it into place; and ``--from-scene``."""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from mst import InputError, MstError
from mst.pipeline.synth.config import DYNAMIC, SCENARIOS, SynthConfig
from mst.pipeline.synth.core import SynthResult, plan_sequence, render_frame
from mst.pipeline.synth.scene import load_model_triangles
from mst.pipeline.synth.writers import (
    SCENE_VERSION,
    H264Writer,
    _commit_out_dir,
    _prepare_out_dir,
    _sha256,
    write_frame,
    write_metadata,
)


def synthesize(scenario: str, model_path: str | os.PathLike, out_dir: str | os.PathLike,
               config: SynthConfig | None = None, progress: Callable[[int], None] | None = None,
               overwrite: bool = False, model_source: str | None = None) -> dict:
    """Render a synthetic sequence of ``model_path`` along ``scenario`` into ``out_dir`` (layout:
    :mod:`mst.pipeline.synth`).

    All outputs appear at once (written in a temporary folder beside ``out_dir``, then moved).
    ``model_source`` is the model path recorded in scene.json (default ``model_path``).
    Returns the summary dict (:class:`SynthResult` fields and the effective ``config``).
    """
    cfg = config or SynthConfig()
    if scenario not in SCENARIOS:
        raise InputError(None, f"unknown scenario {scenario!r} (expected one of {', '.join(SCENARIOS)})")
    if scenario in DYNAMIC:  # moving object / interrupted view
        from mst.pipeline.synth.dynamic import synthesize_dynamic

        return synthesize_dynamic(scenario, model_path, out_dir, cfg, progress=progress, overwrite=overwrite)
    model_path = Path(model_path)
    V, F = load_model_triangles(model_path)
    t_start = time.perf_counter()
    plan = plan_sequence(scenario, cfg, V, F)
    t_setup = time.perf_counter() - t_start
    tmp = _prepare_out_dir(Path(out_dir), overwrite)
    try:
        rows, render_s = _render_into(tmp, plan, cfg, progress)
        write_metadata(tmp, plan, cfg, scenario, V, F, rows,
                       str(model_source if model_source is not None else model_path))
        _commit_out_dir(tmp, Path(out_dir))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    p, cam, frames = plan.scene.params, plan.cam, len(plan.T_model_cam)
    model_frac = np.array([r[2] for r in rows]) / float(cam.width * cam.height)
    result = SynthResult(
        out_dir=str(out_dir), scenario=scenario, base=p["base"], frames=frames, drop=p["drop"], fps=float(cfg.fps),
        width=cam.width, height=cam.height, focal_px=cam.fx, depth=bool(cfg.depth), distance_m=p["distance"],
        speed_m_s=p["speed"], clicks=len(plan.click_X), frames_without_model=int(np.count_nonzero(model_frac == 0)),
        triangles={"model": len(F), "scene": len(plan.mesh[1])}, setup_s=t_setup,
        render_ms_per_frame=1000.0 * render_s / max(frames, 1), total_s=time.perf_counter() - t_start)
    return {**result.to_json(), "config": cfg.to_dict()}


def _render_into(tmp: Path, plan, cfg: SynthConfig, progress) -> tuple[list, float]:
    """Render every frame into ``tmp``; returns the frames.csv rows and the rendering time (s)."""
    import cv2

    fps = float(cfg.fps)
    cam = plan.cam
    (tmp / "rgb").mkdir()
    (tmp / "cMo").mkdir()
    if cfg.depth:
        (tmp / "depth").mkdir()
    writer = None
    if cfg.video:
        if cfg.video_codec == "h264":
            writer = H264Writer(tmp / "video.mp4", fps, (cam.width, cam.height))
        else:
            writer = cv2.VideoWriter(str(tmp / "video.mp4"), cv2.VideoWriter_fourcc(*"mp4v"), fps,
                                     (cam.width, cam.height))
            if not writer.isOpened():
                raise MstError("cv2.VideoWriter could not open an mp4v mp4 writer")
    rows, render_s = [], 0.0
    for k in range(len(plan.T_model_cam)):
        t0 = time.perf_counter()
        frame = render_frame(plan, cfg, k)
        render_s += time.perf_counter() - t0
        write_frame(tmp, frame, plan.T_cam_model[k], writer, cfg.depth)
        rows.append((k, k / fps, frame.model_px, frame.edge_px))
        if progress:
            progress(1)
    if writer is not None:
        writer.release()
    return rows, render_s


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
        scenario = spec["scenario"]
        model = spec["model"]
        config = spec["config"]
    except (KeyError, TypeError) as e:
        raise InputError(p, f"bad scene file (no {e})") from None
    cfg = SynthConfig.from_dict(config, source=p)  # a bad or unknown setting: a ConfigError naming it and the file
    mp = p.parent / model.get("file", "model.obj")
    if not mp.is_file():
        raise InputError(mp, "model file named in scene.json does not exist")
    if model.get("sha256") and _sha256(mp) != model["sha256"]:
        raise InputError(mp, "model.obj does not match the sha256 recorded in scene.json")
    return synthesize(scenario, mp, out_dir, cfg, progress=progress, overwrite=overwrite,
                      model_source=model.get("source"))
