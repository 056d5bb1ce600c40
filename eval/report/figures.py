"""The report's images, as PNG bytes: the C2M histogram and the colour-mapped cloud views, the
trajectory figure, the per-frame status timeline and the overlay strip.

The histogram and the trajectory figure are the images the CLI's ``--plot`` options write: the file
itself when the run kept it (a batch's ``c2m_hist.png``, ``eval_traj.png``), else the same plotting
function (:mod:`mst.eval.plots`) on the run's files, with the settings its summary records.
"""

from __future__ import annotations

import csv
import io
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mst.eval.report.config import ReportConfig
from mst.eval.report.sources import RunFiles, resolve_path

STATUS_COLOURS = {"model": "#228833", "slam": "#4477aa", "relocalised": "#ee7733", "lost": "#cc3311"}


def _plt():
    from mst.eval.plots import _plt as plots_plt

    return plots_plt()


def _png(fig, dpi: int) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    _plt().close(fig)
    return buf.getvalue()


def _via_file(write) -> bytes:
    """Bytes of the PNG that ``write(path)`` (a :mod:`mst.eval.plots` function) writes."""
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "figure.png"
        write(p)
        return p.read_bytes()


@dataclass
class CloudData:
    points: np.ndarray               #: (n, 3) finite points, model frame
    distances: np.ndarray | None     #: their unsigned C2M distances (None: not computed)
    source: str


def cloud_data(run: RunFiles, cfg: ReportConfig) -> CloudData | None:
    """The run's cloud (the one its c2m summary names, else cloud.ply) and, when the c2m summary and its
    mesh are there, the distances, recomputed with the recorded settings (the same numbers as the run)."""
    from mst.eval.cloud_io import read_cloud

    c2m = run.summaries.get("c2m") or {}
    cloud = resolve_path(c2m.get("cloud"), run.folder) or run.file("cloud.ply")
    if cloud is None:
        return None
    P = read_cloud(cloud)
    P = P[np.isfinite(P).all(axis=1)]
    mesh = resolve_path(c2m.get("mesh"), run.folder)
    d = None
    if mesh is not None and 0 < len(P) <= cfg.c2m_max_points:
        from mst.eval.c2m.config import C2MConfig
        from mst.eval.c2m.driver import c2m as c2m_core
        from mst.eval.c2m.runner import load_mesh_triangles

        c = C2MConfig.from_dict(c2m.get("config") or {})
        res = c2m_core(P, load_mesh_triangles(mesh), c.replace(signed=False))
        if len(res.distances) == len(P):
            d = np.asarray(res.distances, np.float64)
    return CloudData(P, d, str(cloud))


def c2m_histogram(run: RunFiles, data: CloudData | None) -> bytes | None:
    kept = run.file("c2m_hist.png")
    if kept is not None:
        return kept.read_bytes()
    c2m = run.summaries.get("c2m")
    if c2m is None or data is None or data.distances is None:
        return None
    from mst.eval.plots import c2m_histogram as plot

    thresholds = [r["max_dist"] for r in c2m["thresholds"]]
    percents = [r["percent"] for r in c2m["thresholds"]]
    title = f"C2M {Path(c2m.get('cloud') or data.source).name} vs {Path(c2m.get('mesh') or '').name}"  # as mst c2m --plot
    return _via_file(lambda p: plot(p, data.distances, thresholds, title=title, percents=percents))


def _raster(u: np.ndarray, v: np.ndarray, c: np.ndarray, px: int) -> tuple[np.ndarray, tuple[float, ...]]:
    """The mean of ``c`` per pixel of a ``px``-wide grid over (u, v) (NaN where no point falls), and its extent."""
    lo_u, hi_u, lo_v, hi_v = float(u.min()), float(u.max()), float(v.min()), float(v.max())
    size = max(hi_u - lo_u, hi_v - lo_v, 1e-9) / px
    nu, nv = max(1, int((hi_u - lo_u) / size) + 1), max(1, int((hi_v - lo_v) / size) + 1)
    iu = np.minimum(((u - lo_u) / size).astype(np.int64), nu - 1)
    iv = np.minimum(((hi_v - v) / size).astype(np.int64), nv - 1)
    flat = iv * nu + iu
    n = np.bincount(flat, minlength=nu * nv)
    total = np.bincount(flat, weights=c, minlength=nu * nv)
    with np.errstate(invalid="ignore", divide="ignore"):
        img = np.where(n > 0, total / n, np.nan).reshape(nv, nu)
    return img, (lo_u, lo_u + nu * size, hi_v - nv * size, hi_v)


def cloud_views(data: CloudData, cfg: ReportConfig) -> bytes:
    """Top (X-Y) and side (X-Z) views of the cloud, coloured by C2M distance (else by height), each pixel
    the mean over the points that fall in it."""
    plt = _plt()
    step = max(1, len(data.points) // cfg.cloud_points)
    P = data.points[::step]
    if data.distances is not None:
        c = data.distances[::step]
        lo, hi = 0.0, float(np.percentile(c, 99)) if len(c) else 1.0
        label, cmap = "C2M distance [m] (pixel mean)", "viridis"
    else:
        c = P[:, 2]
        lo, hi = (float(c.min()), float(c.max())) if len(c) else (0.0, 1.0)
        label, cmap = "height Z [m] (pixel mean)", "terrain"
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    for ax, (i, j, name) in zip(axes, ((0, 1, "top view (X-Y)"), (0, 2, "side view (X-Z)"))):
        img, extent = _raster(P[:, i], P[:, j], c, 500)
        im = ax.imshow(img, extent=extent, cmap=cmap, vmin=lo, vmax=max(hi, lo + 1e-9), interpolation="nearest")
        ax.set_xlabel("X [m]")
        ax.set_ylabel("YZ"[j - 1] + " [m]")
        ax.set_title(f"{name}, {len(P):,} of {len(data.points):,} points")
    fig.colorbar(im, ax=list(axes), label=label, shrink=0.85)
    return _png(fig, cfg.dpi)


def trajectory(run: RunFiles) -> bytes | None:
    kept = run.file("eval_traj.png")
    if kept is not None:
        return kept.read_bytes()
    ev = run.summaries.get("eval")
    if ev is None:
        return None
    est, ref = resolve_path(ev.get("estimate"), run.folder), resolve_path(ev.get("reference"), run.folder)
    if est is None or ref is None:
        return None
    from mst.eval.plots import trajectory_figure
    from mst.eval.traj import TrajConfig, evaluate_trajectories

    align = ev.get("align", "se3")
    recorded = ev.get("config")  # the effective settings of the run (older summaries: align and tolerance)
    tc = TrajConfig.from_dict(recorded) if recorded else TrajConfig(align=align, t_max_diff_s=ev.get("t_max_diff_s", 0.01))
    res = evaluate_trajectories(est, ref, tc)
    series = res.series
    gaps = [(g["t_start"], g["t_end"]) for g in res.gaps["ranges"]]
    return _via_file(lambda p: trajectory_figure(p, series.t_ref_all, series.xyz_ref_all, series.t, series.xyz_est,
                                                 series.dxyz, series.dyaw, gaps,
                                                 title=f"{est.name} vs {ref.name} (align {tc.align})"))


def read_status(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def timeline(rows: list[dict[str, str]], cfg: ReportConfig) -> bytes:
    """Per frame: the status as a colour band and the health score below."""
    from matplotlib.colors import ListedColormap

    plt = _plt()
    names = list(STATUS_COLOURS)
    frames = np.array([int(r["frame"]) for r in rows])
    idx = np.array([names.index(r["status"]) if r["status"] in names else 3 for r in rows])
    score = np.array([float(r["score"]) if r.get("score") not in (None, "", "nan") else np.nan for r in rows])
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(13, 3.2), sharex=True, gridspec_kw={"height_ratios": [1, 2]})
    a1.imshow(idx[None, :], aspect="auto", cmap=ListedColormap(list(STATUS_COLOURS.values())), vmin=-0.5,
              vmax=len(names) - 0.5, extent=(frames.min() - 0.5, frames.max() + 0.5, 0, 1), interpolation="nearest")
    a1.set_yticks([])
    a1.set_title("  ".join(f"{n}: {int((idx == k).sum())}" for k, n in enumerate(names)))
    for n in names:
        a1.plot([], [], "s", color=STATUS_COLOURS[n], label=n)
    a1.legend(loc="upper left", bbox_to_anchor=(1.0, 1.3), fontsize=8, frameon=False)
    a2.plot(frames, score, ".-", ms=3, lw=0.8, color="#333333")
    a2.axhline(0, color="#cc3311", lw=0.6, ls="--")
    a2.set_ylabel("health score")
    a2.set_xlabel("frame")
    fig.tight_layout()
    return _png(fig, cfg.dpi)


def _model_edges(model_path: str) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, (k, 2) vertex index pairs) of every face loop and hole of a polygon model."""
    from mst.meshtools.formats import load_model

    m = load_model(model_path)
    pairs = set()
    for loops in ([f] + list(h) for f, h in zip(m.faces, m.holes or [[]] * len(m.faces))):
        for loop in loops:
            for a, b in zip(loop, np.roll(loop, -1)):
                pairs.add((int(min(a, b)), int(max(a, b))))
    if len(m.lines):
        pairs.update((int(min(a, b)), int(max(a, b))) for a, b in m.lines)
    return m.vertices, np.array(sorted(pairs), np.int64).reshape(-1, 2)


def overlay_strip(run: RunFiles, rows: list[dict[str, str]], cfg: ReportConfig) -> list[tuple[int, str, bytes]]:
    """(frame, status, PNG) of ``cfg.overlay_frames`` evenly spaced frames with the model drawn at the
    tracked pose (its wireframe, in the status colour); a lost frame shows the image alone."""
    import cv2

    from mst.core.camera import read_camera
    from mst.core.poses import inv_T, transform_points
    from mst.core.trajectory import read_tum
    from mst.pipeline.frames import open_frames

    if cfg.overlay_frames == 0 or not rows or run.traj is None or not (run.frames and run.model and run.camera):
        return []
    cam = read_camera(run.camera)
    V, E = _model_edges(run.model)
    t, T_model_cam = read_tum(run.traj)
    times = np.array([float(r["time"]) for r in rows])
    pick = np.unique(np.linspace(0, len(rows) - 1, min(cfg.overlay_frames, len(rows))).round().astype(int))
    wanted = {int(rows[k]["frame"]): k for k in pick}
    src = open_frames(run.frames, fps=run.fps)
    out = []
    for index, _, img in src:
        k = wanted.get(index)
        if k is None:
            if index > max(wanted):
                break
            continue
        status = rows[k]["status"]
        j = int(np.argmin(np.abs(t - times[k]))) if len(t) else -1
        if status != "lost" and j >= 0 and abs(t[j] - times[k]) < 1e-3:
            Xc = transform_points(inv_T(T_model_cam[j]), V)
            ok = Xc[:, 2] > 1e-6
            uv = np.full((len(V), 2), np.nan)
            uv[ok] = cam.project(Xc[ok])
            colour = tuple(int(STATUS_COLOURS.get(status, "#228833")[i:i + 2], 16) for i in (5, 3, 1))  # BGR
            for a, b in E:
                if ok[a] and ok[b]:
                    cv2.line(img, tuple(np.round(uv[a]).astype(int)), tuple(np.round(uv[b]).astype(int)), colour, 1,
                             cv2.LINE_AA)
        scale = cfg.overlay_width_px / img.shape[1]
        if abs(scale - 1) > 1e-6:
            img = cv2.resize(img, (cfg.overlay_width_px, max(1, round(img.shape[0] * scale))),
                             interpolation=cv2.INTER_AREA)
        ok, png = cv2.imencode(".png", img)
        if ok:
            out.append((index, status, png.tobytes()))
    return out
