"""The stages of a batch: each sequence's chain as ``mst`` command lines with their inputs and outputs.

Per sequence (folder ``OUT/<name>``): convert-model (once per model and convert options, in
``OUT/models/<stem>``; ``.wrl``/``.cao`` models are used as they are), init (unless the manifest
gives a pose file), track, fuse (when depth is given), c2m (depth and a reference mesh), eval traj
(a ground truth). Every path in a command line is absolute, so a stage runs the same on any worker
that sees the same file system.
"""

from __future__ import annotations

import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from mst.eval.batch.manifest import OUT_PREFIX, Manifest, SequenceSpec, StageOptions

POLYGON_SUFFIXES = (".wrl", ".cao")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".pgm", ".ppm")


@dataclass
class Stage:
    """One command of the batch (a node of the task graph)."""

    id: str                       #: "house-orbit/track", "models/house/convert-model"
    unit: str                     #: the folder name below OUT: a sequence or "models/<stem>"
    name: str                     #: the stage: convert-model, init, track, fuse, c2m, eval
    folder: str                   #: absolute folder of the unit (holds its state file)
    argv: tuple[str, ...]         #: the mst command line, without "mst"
    inputs: tuple[str, ...]       #: files/folders whose content decides a rerun
    outputs: tuple[str, ...]      #: every file the command writes
    summary: str | None           #: where its --json summary (stdout) is kept
    deps: tuple[str, ...] = ()    #: ids of the stages it needs


def first_frame(frames: str) -> str:
    """The first image of a frames folder or pattern; a video (or single image) stands for itself."""
    from mst.eval.batch.state import _expand

    if os.path.isfile(frames):
        return frames
    files = [f for f in _expand(frames) if f.lower().endswith(IMAGE_SUFFIXES)]
    if os.path.isdir(frames):
        files = [f for f in files if os.path.dirname(f) == frames.rstrip("/")]
    return files[0] if files else frames


def _opts(spec: SequenceSpec, stage: str, folder: Path) -> StageOptions:
    o = spec.options.get(stage, StageOptions())
    place = lambda a: str(folder / a[len(OUT_PREFIX):]) if a.startswith(OUT_PREFIX) else a  # noqa: E731
    return StageOptions(tuple(place(a) for a in o.args), o.inputs, tuple(str(folder / p) for p in o.outputs))


def _model_stages(manifest: Manifest, out: Path) -> tuple[list[Stage], dict[str, tuple[str, str | None]]]:
    """convert-model stages (one per model + options) and, per sequence, (model file, stage id)."""
    stages: list[Stage] = []
    by_key: dict[tuple, Stage] = {}
    per_seq: dict[str, tuple[str, str | None]] = {}
    stems: dict[str, int] = {}
    for s in manifest.sequences:
        if Path(s.model).suffix.lower() in POLYGON_SUFFIXES:
            per_seq[s.name] = (s.model, None)
            continue
        o = s.options.get("convert-model", StageOptions())
        key = (s.model, o.args)
        st = by_key.get(key)
        if st is None:
            stem = Path(s.model).stem or "model"
            stems[stem] = stems.get(stem, 0) + 1
            unit = f"models/{stem}" if stems[stem] == 1 else \
                f"models/{stem}-{hashlib.sha256(repr(key).encode()).hexdigest()[:8]}"
            folder = out / unit
            wrl = str(folder / "model.wrl")
            st = Stage(f"{unit}/convert-model", unit, "convert-model", str(folder),
                       ("convert-model", s.model, "-o", wrl, "--json", "-q", *o.args),
                       (s.model, *o.inputs), (wrl,), str(folder / "convert-model.json"))
            by_key[key] = st
            stages.append(st)
        per_seq[s.name] = (st.outputs[0], st.id)
    return stages, per_seq


def _sequence_stages(s: SequenceSpec, out: Path, model: str, model_stage: str | None) -> list[Stage]:
    folder = out / s.name
    f = str(folder)
    stages: list[Stage] = []
    model_deps = (model_stage,) if model_stage else ()

    def add(name: str, argv: list[str], inputs: list[str], outputs: list[str], summary: str | None,
            deps: tuple[str, ...]) -> Stage:
        o = _opts(s, name, folder)
        st = Stage(f"{s.name}/{name}", s.name, name, f, (*argv, "--json", "-q", *o.args),
                   (*inputs, *o.inputs), (*outputs, *o.outputs), summary, deps)
        stages.append(st)
        return st

    fps = ["--fps", repr(s.fps)] if s.fps is not None else []
    pose, pose_deps = s.init, ()
    if pose is None:
        pose = str(folder / "pose0.txt")
        argv = ["init", "--model", model, "--camera", s.camera]
        inputs = [model, s.camera]
        if s.clicks is not None:
            argv += ["--clicks", s.clicks] + (["--points", s.points] if s.points else [])
            inputs += [s.clicks] + ([s.points] if s.points else [])
            if s.options.get("init", StageOptions()).outputs:  # an overlay needs the image
                argv += ["--image", first_frame(s.frames)]
                inputs.append(first_frame(s.frames))
        else:
            argv += ["--from-nav", s.nav, "--image", first_frame(s.frames)]
            inputs += [s.nav, first_frame(s.frames)]
        pose_deps = (add("init", [*argv, "-o", pose], inputs, [pose], f"{f}/init.json", model_deps).id,)
    traj = str(folder / "traj.txt")
    depth = ["--depth", s.depth] if s.depth else []
    track = add("track", ["track", s.frames, "--model", model, "--camera", s.camera, "--init", pose, "-o", traj,
                          *depth, *fps],
                [s.frames, model, s.camera, pose, *([s.depth] if s.depth else [])],
                [traj, f"{f}/traj.csv", f"{f}/traj.cov.csv", f"{f}/traj.json"], None, model_deps + pose_deps)
    if s.depth:
        cloud = f"{f}/cloud.ply"
        fuse = add("fuse", ["fuse", "--traj", traj, "--depth", s.depth, "--camera", s.camera, "-o", cloud, *fps],
                   [traj, s.depth, s.camera], [cloud], f"{f}/fuse.json", (track.id,))
        if s.reference:
            add("c2m", ["c2m", cloud, s.reference, "-o", f"{f}/cloud_c2m.ply", "--markdown", f"{f}/c2m.md",
                        "--plot", f"{f}/c2m_hist.png"],
                [cloud, s.reference], [f"{f}/cloud_c2m.ply", f"{f}/c2m.md", f"{f}/c2m_hist.png"],
                f"{f}/c2m.json", (fuse.id,))
    if s.gt:
        add("eval", ["eval", "traj", traj, s.gt, "--plot", f"{f}/eval_traj.png"], [traj, s.gt],
            [f"{f}/eval_traj.png"], f"{f}/eval.json", (track.id,))
    return stages


def build_plan(manifest: Manifest, out: str | os.PathLike) -> list[Stage]:
    """Every stage of the batch, each after the stages it needs."""
    out = Path(out).resolve()
    stages, models = _model_stages(manifest, out)
    for s in manifest.sequences:
        stages += _sequence_stages(s, out, *models[s.name])
    return stages


def sequences_of(stage: Stage, plan: list[Stage]) -> list[str]:
    """The sequences a stage serves (a model conversion: all that use the model)."""
    if not stage.unit.startswith("models/"):
        return [stage.unit]
    return sorted({st.unit for st in plan if stage.id in st.deps})
