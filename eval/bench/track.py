"""Tracking speed: median and p95 per-frame time (decoding excluded), 640x480, edges-only and --klt.

Sequences: the real ``teabox.mp4`` (ViSP's teabox settings; skipped when ../shared/data is absent)
and a rendered orbit around a non-convex (L-shaped) building. Frames are decoded and converted to
gray first; the clock covers ``EdgeTracker.track`` + ``accept`` (visibility, moving edges, VVS,
health, KLT). Both wall-clock and CPU (process) time are reported: on a loaded shared machine the
CPU time is the stable number. The first frame (3 initialisation passes) is excluded.

Targets (issue #5): median <= 5 ms edges-only, <= 10 ms with KLT (ViSP C++ on the same 2-core
machine: 1.2 / 2.1 ms). A whole ``mst track`` command is also timed (start-up, decoding, I/O).

Issue #14: each timed mode is followed by its per-frame budget (:func:`_budget_row`: visibility and
sampling, moving-edge search, VVS, KLT, health evidence, Python overhead), and the ViSP rows (when
the runner is built; ``VISP_ANCHOR=/path/visp_mbt_anchor``) state mst's median of the same mode in
this run and the ratio (target <= 1.0), on teabox and on the rendered L-building orbit (ViSP with
and without its scanline hidden-line removal, with and without its projection error; the target is
judged where ViSP checks each pose as mst does, see :func:`_visp_orbit_rows`). Both trackers run 5
times, in turn (an mst run, then a ViSP run: both see the same load), and the target is judged on each
frame's fastest run (median over frames): on the shared 2-core machine a frame
that the scheduler interrupted in one run is not interrupted in all, while a single run's wall
median of the longer hybrid frames was 2-3x their CPU time (for ViSP's as for mst's). Run alone: ``python -m mst.eval.bench.track``.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared" / "data"


def _frame_min_median(runs: list[np.ndarray]) -> float:
    """Median over frames of each frame's fastest time over repeated runs (ms): the load-robust
    figure (a frame interrupted in one run is not in another; the minimum over runs is the
    frame's uninterrupted time, as ``timeit`` takes the minimum), used for both trackers alike."""
    n = min(len(r) for r in runs)
    return float(np.median(np.min(np.stack([np.asarray(r[:n]) for r in runs]), axis=0)))


def _one_run(model, cam, cfg, grays, T0) -> tuple[np.ndarray, np.ndarray, int, list]:
    """One mst run over ``grays`` (``EdgeTracker.track`` + ``accept``, the first frame from ``T0``):
    ``(wall_ms, cpu_ms, lost, poses)``, the per-frame wall and process CPU times (ms, the first frame
    excluded: its 3 initialisation passes), the frames lost, and each frame's T_cam_model (a lost frame
    keeps the previous pose)."""
    from mst.pipeline.tracking import EdgeTracker

    tr = EdgeTracker(model, cam, cfg)
    T, wall, cpu, lost, poses = T0, [], [], 0, []
    for k, g in enumerate(grays):
        t0, c0 = time.perf_counter(), time.process_time()
        fr = tr.track(g, T, first=k == 0)
        if fr.healthy:
            tr.accept(g, fr.T_cam_model)
            T = fr.T_cam_model
        else:
            lost += 1
        if k > 0:
            wall.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
        poses.append(T)
    return np.array(wall), np.array(cpu), lost, poses


def _time_tracker(model, cam, cfg, grays, T0, repeats: int = 5, truth=None) -> dict:
    """Per-frame times of ``repeats`` runs over ``grays`` (:func:`_one_run`); with ``truth`` (F, 4, 4)
    T_cam_model, the first run's camera-position error (mm; a lost frame keeps the previous pose)."""
    runs, cpus, lost, poses = [], [], 0, []
    for r in range(repeats):
        wall_r, cpu_r, lost_r, poses_r = _one_run(model, cam, cfg, grays, T0)
        runs.append(wall_r)
        cpus.append(cpu_r)
        if r == 0:
            lost, poses = lost_r, poses_r
    w, c = np.concatenate(runs), np.concatenate(cpus)
    out = {"frames": len(grays), "lost": lost, "median_ms": float(np.median(w)), "p95_ms": float(np.percentile(w, 95)),
           "cpu_median_ms": float(np.median(c)), "cpu_p95_ms": float(np.percentile(c, 95)),
           "frame_min_median_ms": _frame_min_median(runs)}
    if truth is not None:
        from mst.core.poses import inv_T, pose_error

        dt, _dr = pose_error(inv_T(np.asarray(poses)), inv_T(np.asarray(truth)[: len(poses)]))
        out["vs_truth_median_mm"] = float(np.median(dt) * 1e3)
        out["vs_truth_max_mm"] = float(dt.max() * 1e3)
    return out


def _mst_runner(model, cam, cfg, grays, T0):
    """``run(mode)`` -> one mst run's per-frame wall times (ms, :func:`_one_run`) in ViSP's ``edge`` or
    ``hybrid`` mode (``cfg`` without / with KLT): the mst side of the interleaved ViSP comparisons."""
    return lambda mode: _one_run(model, cam, cfg.replace(use_klt=mode == "hybrid"), grays, T0)[0]


def _judge_interleaved(row: dict, mst_runs: list, visp_runs: list, target: str | None) -> None:
    """mst's figures beside ViSP's from runs taken in turn (one mst run, then one ViSP run, ``repeats`` times):
    both trackers see the same load, so the ratio does not drift with it (measured in separate blocks the
    hybrid teabox ratio ranged over 0.84-1.06 between full bench runs on the shared 2-core machine). The
    judged figure is each frame's fastest run for both (median over frames)."""
    row["mst_median_ms"] = round(float(np.median(np.concatenate(mst_runs))), 3)
    row["ratio_vs_visp"] = round(row["mst_median_ms"] / float(np.median(np.concatenate(visp_runs))), 3)
    row["mst_frame_min_median_ms"] = round(_frame_min_median(mst_runs), 3)
    row["ratio_vs_visp_frame_min"] = round(row["mst_frame_min_median_ms"] / row["frame_min_median_ms"], 3)
    row["interleaved_runs"] = len(mst_runs)
    if target is not None:
        row["target"] = target
        row["ok"] = bool(row["ratio_vs_visp_frame_min"] <= 1.0)


def _rows(name: str, model, cam, cfg, grays, T0, truth=None) -> list[dict]:
    out = []
    for klt, target in ((False, 5.0), (True, 10.0)):
        c = cfg.replace(use_klt=klt)
        r = _time_tracker(model, cam, c, grays, T0, truth=truth)
        r["bench"] = f"track {name} {'edges+klt' if klt else 'edges'} 640x480"
        r["target"] = f"median <= {target:g} ms (CPU time)"
        r["ok"] = bool(r["cpu_median_ms"] <= target and r["lost"] == 0)
        out.append(r)
        out.append(_budget_row(f"{name} {'edges+klt' if klt else 'edges'}", model, cam, c, grays, T0, r["median_ms"]))
    return out


#: stages of the per-frame budget: (name, function names whose cumulative time counts for it)
BUDGET_STAGES = (
    ("visibility_sampling", ("visible_samples",)),
    ("moving_edge_search", ("search_edges",)),
    ("vvs", ("solve_pose",)),
    ("klt_tracking", ("_klt_track",)),  # the frame's pyramid (built once) and the forward-backward LK
    ("klt_detection", ("_klt_points",)),  # re-detection (on few frames: its share of the whole run)
    ("health_evidence", ("evidence", "_absolute_health")),
)


def _budget_row(name: str, model, cam, cfg, grays, T0, median_ms: float) -> dict:
    """Per-frame budget of ``EdgeTracker.track`` + ``accept`` (issue #14), measured with cProfile on
    the same frames: each stage's cumulative time (functions of :data:`BUDGET_STAGES`; nested calls
    are counted once, in the outermost stage listed), the rest as ``python_overhead``. The profiler
    slows Python-heavy code more than compiled code, so the shares are given and the ms are those
    shares of the un-profiled ``median_ms`` (an estimate)."""
    import cProfile
    import pstats

    pr = cProfile.Profile()
    pr.enable()
    _one_run(model, cam, cfg, grays, T0)
    pr.disable()
    st = pstats.Stats(pr).stats  # {(file, line, func): (cc, nc, tt, ct, callers)}
    cum: dict[str, float] = {}
    for (_f, _l, fn), (_cc, _nc, _tt, ct, _callers) in st.items():
        cum[fn] = cum.get(fn, 0.0) + ct
    total = cum.get("track", 0.0) + cum.get("accept", 0.0)
    row = {"bench": f"track {name} per-frame budget (cProfile shares x median)", "median_ms": round(median_ms, 3)}
    used = 0.0
    for stage, fns in BUDGET_STAGES:
        t = max((cum.get(f, 0.0) for f in fns), default=0.0)
        used += t
        row[f"{stage}_share"] = round(t / total, 3) if total else None
        row[f"{stage}_ms"] = round(median_ms * t / total, 3) if total else None
    row["python_overhead_share"] = round(1 - used / total, 3) if total else None
    row["python_overhead_ms"] = round(median_ms * (1 - used / total), 3) if total else None
    return row


def _visp_anchor_rows(tb: Path, workdir: Path, mst_run, mst_cpu_ms: dict) -> list[dict]:
    """ViSP's own tracker on the same frames, when its runner is built (../shared/tools/visp-anchor,
    ``$VISP_ANCHOR`` or /tmp/visp_build/visp_mbt_anchor): its median time, and how far the mst and
    ViSP trajectories are apart (camera position mm, rotation deg). Each ViSP run follows an mst run of
    the same mode (``mst_run``, :func:`_mst_runner`) and the ratio is judged on those
    (:func:`_judge_interleaved`); ``mst_cpu_ms`` (mode -> the teabox row's CPU median) is reported beside."""
    import os
    import subprocess

    from mst.core.poses import inv_T, pose_error
    from mst.core.trajectory import read_tum
    from mst.eval.bench.harness import mst_cmd

    exe = Path(os.environ.get("VISP_ANCHOR", "/tmp/visp_build/visp_mbt_anchor"))
    if not exe.is_file():
        print("[bench track] ViSP anchor not built: no side-by-side rows", file=sys.stderr)
        return []
    out = []
    for mode, flag in (("edge", "--no-klt"), ("hybrid", "--klt")):
        vf = workdir / f"visp_{mode}.txt"
        visp_runs, mst_runs = [], []
        for _ in range(5):  # as mst's rows: 5 runs, each frame's fastest for the load-robust figure
            mst_runs.append(mst_run(mode))
            subprocess.run([str(exe), "--mode", mode, "--model", str(tb / "teabox.cao"), "--input", str(tb / "teabox.mp4"),
                            "--cam", "839.21470", "839.44555", "325.66776", "243.69727", "--init-clicks",
                            str(tb / "teabox.clicks"), "--init-points", str(tb / "teabox.init"), "--out", str(vf)],
                           check=True, capture_output=True)
            visp_runs.append(np.loadtxt(vf, comments="#")[1:, 14])  # the first frame: mst's rows exclude it too
        a = np.loadtxt(vf, comments="#")
        T = np.tile(np.eye(4), (len(a), 1, 1))
        T[:, :3, :] = a[:, 1:13].reshape(-1, 3, 4)
        mf = workdir / f"mst_{mode}.txt"
        subprocess.run(mst_cmd("track", tb / "teabox.mp4", "--model", tb / "teabox.cao", "--camera", tb / "teabox.xml",
                               "--init", workdir / "pose0.txt", "-o", mf, "-q", flag), check=True)
        _, T_mst = read_tum(mf)
        dt, dr = pose_error(T_mst, inv_T(T)[: len(T_mst)])
        row = {"bench": f"ViSP 3.5 {mode} on teabox (same machine, now)", "median_ms": float(np.median(a[:, 14])),
               "mst_vs_visp_median_mm": float(np.median(dt) * 1e3), "mst_vs_visp_max_mm": float(dt.max() * 1e3),
               "mst_vs_visp_median_deg": float(np.median(dr)), "mst_vs_visp_max_deg": float(dr.max())}
        row["frame_min_median_ms"] = round(_frame_min_median(visp_runs), 3)
        # issue #14, judged on runs in turn with ViSP's
        _judge_interleaved(row, mst_runs, visp_runs,
                           "mst median <= 1.0 x ViSP's (same run; per-frame fastest of 5 runs, both trackers), interleaved")
        if mode in mst_cpu_ms:
            # on a loaded machine mst's wall median is inflated by waiting; its CPU median is not (ViSP's runner
            # reports wall times only: its CPU median is not known here). The teabox row's, not interleaved
            row["mst_cpu_median_ms"] = round(mst_cpu_ms[mode], 3)
            row["ratio_vs_visp_mst_cpu"] = round(mst_cpu_ms[mode] / row["median_ms"], 3)
        out.append(row)
    return out


def _visp_orbit_rows(m, cam, poses, grays, workdir: Path, mst_rows: list[dict], mst_run, repeats: int = 5) -> list[dict]:
    """ViSP's tracker on the rendered L-building orbit (issue #14: "on a synthetic building orbit"),
    when its runner is built: the same frames (PNG), the model as ``.cao``, the true first pose, the
    intrinsics and mst's face angles (80/85 deg; range, step, mask, threshold are the defaults both
    share). The model is non-convex, so ViSP runs with its scanline visibility (hidden lines, the
    work mst's depth buffer does) and without (the cheaper, less faithful mode), each with and
    without its projection error (``getProjectionError``, its per-frame health check: the runner's
    default, on in the teabox rows; mst checks every pose with its projection error and image
    evidence, so the like-for-like rows, where the target is judged, are those with it on).

    Each configuration runs ``repeats`` times; its figure, as mst's, is each frame's fastest run
    (median over frames; the load-robust figure of the teabox rows); the wall median of all runs
    beside it. Also the distance of each trajectory from the truth (camera position, mm). Each ViSP run
    follows an mst run of the same mode (``mst_run``, :func:`_mst_runner`), and mst's figures and the
    ratio come from those (:func:`_judge_interleaved`); ``mst_rows`` (the orbit rows) give its CPU median
    and its distance from the truth."""
    import os
    import subprocess

    import cv2

    from mst.core.poses import inv_T, pose_error
    from mst.meshtools.formats import save_model

    exe = Path(os.environ.get("VISP_ANCHOR", "/tmp/visp_build/visp_mbt_anchor"))
    if not exe.is_file():
        return []
    d = workdir / "visp_orbit"
    d.mkdir(parents=True, exist_ok=True)
    for k, g in enumerate(grays):
        cv2.imwrite(str(d / f"{k:06d}.png"), g)
    save_model(d / "l_building.cao", m)
    np.savetxt(d / "cMo0.txt", np.asarray(poses[0]))  # the runner reads a 4x4 cMo
    mst_med = {("hybrid" if "klt" in r["bench"] else "edge"): r for r in mst_rows if "frames" in r}
    out = []
    for mode, scan, proj in (("edge", 1, 1), ("edge", 0, 1), ("edge", 0, 0), ("hybrid", 1, 1), ("hybrid", 0, 1)):
        vf = d / f"visp_{mode}_scan{scan}_proj{proj}.txt"
        runs, mst_runs = [], []
        for _ in range(repeats):
            mst_runs.append(mst_run(mode))
            subprocess.run([str(exe), "--mode", mode, "--model", str(d / "l_building.cao"), "--input", str(d / "%06d.png"),
                            "--cam", str(cam.fx), str(cam.fy), str(cam.cx), str(cam.cy), "--init-pose", str(d / "cMo0.txt"),
                            "--angle-appear", "80", "--angle-disappear", "85", "--scanline", str(scan), "--proj-err",
                            str(proj), "--out", str(vf)], check=True, capture_output=True)
            a = np.loadtxt(vf, comments="#")
            runs.append(a[1:, 14])  # the first frame: mst's rows exclude it too
        T = np.tile(np.eye(4), (len(a), 1, 1))
        T[:, :3, :] = a[:, 1:13].reshape(-1, 3, 4)
        dt, _ = pose_error(inv_T(T), inv_T(np.asarray(poses[: len(T)])))
        like_for_like = proj == 1
        row = {"bench": f"ViSP 3.5 {mode} on the L-building orbit (scanline {scan}, projection error {'on' if proj else 'off'}; "
                        "same machine, now)",
               "median_ms": float(np.median(np.concatenate(runs))), "frame_min_median_ms": round(_frame_min_median(runs), 3),
               "visp_vs_truth_median_mm": float(np.median(dt) * 1e3), "visp_vs_truth_max_mm": float(dt.max() * 1e3)}
        r = mst_med.get(mode)
        target = ("mst <= 1.0 x ViSP's (same run; per-frame fastest of 5 runs, both trackers; both check each pose)"
                  if like_for_like else None)
        _judge_interleaved(row, mst_runs, runs, None if target is None else target + ", interleaved")
        if r is not None:
            row["mst_cpu_median_ms"] = round(r["cpu_median_ms"], 3)  # the orbit row's (not interleaved)
            if "vs_truth_median_mm" in r:
                row["mst_vs_truth_median_mm"] = round(r["vs_truth_median_mm"], 3)
        if target is None:
            row["note"] = "ViSP without any per-frame health check (mst always checks): shown, not judged"
        out.append(row)
    return out


def _default_mode_rows(tb: Path, workdir: Path, grays: list, model, cam, cfg, T0) -> list[dict]:
    """The default mode (``--slam auto`` without depth: edges + KLT, the mono aid on standby, the
    calibrated health score, the relocaliser learning keyframes and rendered views) through
    ``run_track`` on teabox, per-frame time from its summary (decoding excluded), next to
    ``--slam off``; and the relocaliser's costs: learning a keyframe (ORB on the model's surfaces,
    plus the views rendered from the model with its texture, turned by +-30/60/90 deg) and one
    attempt (ORB on the frame, ratio-test matching against a bounded share of the database,
    RANSAC PnP), the work done per attempt while lost. Times: wall ms (median) and process CPU ms."""
    from mst.pipeline.tracking import EdgeTracker, run_track
    from mst.pipeline.tracking.relocalise import Relocaliser, RelocConfig

    rows = []
    for label, c in (("default mode (edges+KLT, aid on standby, health score, relocaliser)", cfg.replace(aid="auto")),
                     ("--slam off", cfg.replace(aid="off"))):
        t_cpu = time.process_time()
        s = run_track(tb / "teabox.mp4", tb / "teabox.cao", tb / "teabox.xml", workdir / "pose0.txt",
                      workdir / f"traj_{c.aid}.txt", c)
        cpu_ms = (time.process_time() - t_cpu) * 1e3 / max(s["frames"], 1)
        row = {"bench": f"track teabox {label} 640x480", "median_ms": s["median_ms"], "p95_ms": s["p95_ms"],
               "cpu_ms_per_frame_incl_decode": round(cpu_ms, 2), "lost": s["lost"], "aid_wakes": s.get("aid_wakes"),
               "reloc_keyframes": (s.get("relocalisation") or {}).get("keyframes")}
        if c.aid == "auto":
            row.update(target="median <= 5 ms (wall)", ok=bool(s["median_ms"] <= 5.0 and s["lost"] == 0))
        rows.append(row)
    tracker = EdgeTracker(model, cam, cfg)
    for views, name in ((0, "keyframe only"), (RelocConfig().synth_steps, "keyframe + rendered views")):
        rc = RelocConfig(synth_steps=views)
        Relocaliser(tracker, rc).learn(0, grays[0], T0)  # warm-up (numba kernels, ORB)
        ms, cpu, n_views = [], [], 0
        for _ in range(5):
            reloc = Relocaliser(tracker, rc)
            t0, c0 = time.perf_counter(), time.process_time()
            reloc.learn(0, grays[0], T0)
            ms.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
            n_views = reloc.stats["synth_views"]
        rows.append({"bench": f"relocaliser: learn a teabox keyframe ({name})", "median_ms": float(np.median(ms)),
                     "cpu_ms": float(np.median(cpu)), "rendered_views": n_views})
        ms, cpu, found = [], [], 0
        for g in grays[10::5]:
            t0, c0 = time.perf_counter(), time.process_time()
            found += reloc.relocalise(g) is not None
            ms.append((time.perf_counter() - t0) * 1e3)
            cpu.append((time.process_time() - c0) * 1e3)
        rows.append({"bench": f"relocalisation attempt on teabox (learned at frame 0: {name})",
                     "median_ms": float(np.median(ms)), "max_ms": float(np.max(ms)), "cpu_ms": float(np.median(cpu)),
                     "attempts": len(ms), "pnp_poses": found})
    return rows


def run(workdir: Path) -> list[dict]:
    import cv2

    from mst.core.camera import Camera, read_camera
    from mst.eval.bench.harness import mst_cmd, timed_command
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.init_pose import init_from_clicks, read_clicks
    from mst.pipeline.tracking.config import TrackConfig, read_tracker_xml

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    rows: list[dict] = []
    tb = SHARED / "visp-teabox"
    if tb.is_dir():
        cam = read_camera(tb / "teabox.xml").with_size(640, 480)
        cfg = read_tracker_xml(tb / "teabox.xml")
        X, uv = read_clicks(tb / "teabox.clicks", tb / "teabox.init")
        T0 = init_from_clicks(X, uv, cam.K).T_cam_model
        model = load_tracking_model(tb / "teabox.cao")
        cap = cv2.VideoCapture(str(tb / "teabox.mp4"))
        grays = []
        while True:
            ok, img = cap.read()
            if not ok:
                break
            grays.append(cv2.cvtColor(img, cv2.COLOR_BGR2GRAY))
        tb_rows = _rows("teabox", model, cam, cfg, grays, T0)
        rows += tb_rows
        mst_cpu_ms = {("hybrid" if "klt" in r["bench"] else "edge"): r["cpu_median_ms"] for r in tb_rows if "frames" in r}
        from mst.core.trajectory import write_pose_file

        write_pose_file(workdir / "pose0.txt", T0)
        r = timed_command(mst_cmd("track", tb / "teabox.mp4", "--model", tb / "teabox.cao", "--camera", tb / "teabox.xml",
                                  "--init", workdir / "pose0.txt", "-o", workdir / "traj.txt", "-q"))
        rows.append({"bench": "mst track teabox.mp4 (whole command, 39 frames)", "wall_s": r["wall_s"],
                     "peak_rss_mib": r["peak_rss_mib"]})
        rows += _default_mode_rows(tb, workdir, grays, model, cam, cfg, T0)
        rows += _visp_anchor_rows(tb, workdir, _mst_runner(model, cam, cfg, grays, T0), mst_cpu_ms)
    else:
        print(f"[bench track] shared data absent ({tb}): teabox skipped", file=sys.stderr)

    # rendered orbit around an L-shaped building, 640x480
    sys.path.insert(0, str(ROOT / "tests"))
    from synth_helpers import orbit_poses, render_views

    from mst.meshtools.generate import l_shape_model

    m = l_shape_model()
    cam = Camera(600, 600, 319.5, 239.5, 640, 480)
    poses = orbit_poses(m.vertices.mean(0), 22.0, 8.0, 40, 1.0)
    grays = [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in render_views(m, cam, poses)]
    orbit_rows = _rows("L-building orbit", m, cam, TrackConfig(), grays, poses[0], truth=poses)
    rows += orbit_rows
    rows += _visp_orbit_rows(m, cam, poses, grays, workdir, orbit_rows, _mst_runner(m, cam, TrackConfig(), grays, poses[0]))
    return rows


if __name__ == "__main__":
    import json

    for row in run(Path("/tmp/mst-bench-track")):
        print(json.dumps(row))
