"""mst report: the sections of a run folder and of a batch folder, a self-contained page (no network,
no script), settings from a config file, and a real headless browser (skipped without chromium)."""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import run_mst
from test_batch import BOX

SECTIONS = ("Table 1: cloud-to-mesh", "C2M histogram and cloud views", "Trajectory against the reference",
            "Per-frame status and overlay frames", "Overlay frames", "Commands and configurations")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    """A small run folder made without tracking: a box, 8 grey frames, a trajectory around it with a
    lost frame, its ground truth, a cloud on the box, and the c2m / eval summaries of mst itself."""
    import cv2

    from mst.core.camera import Camera, write_camera
    from mst.core.poses import look_at
    from mst.core.trajectory import write_tum
    from mst.eval.cloud_io import write_cloud

    d = tmp_path_factory.mktemp("run")
    (d / "box.obj").write_text(BOX)
    write_camera(d / "camera.json", Camera(130.0, 130.0, 79.5, 59.5, 160, 120))
    (d / "rgb").mkdir()
    rng = np.random.default_rng(0)
    n = 8
    ang = np.linspace(0, 0.6, n)
    T = np.stack([look_at(np.array([6 * np.cos(a), 6 * np.sin(a), 2.5]), np.array([0, 0, 0.6])) for a in ang])
    t = np.arange(n) / 30
    for k in range(n):
        cv2.imwrite(str(d / "rgb" / f"{k:06d}.png"), rng.integers(60, 200, (120, 160, 3), dtype=np.uint8))
    keep = np.arange(n) != 4
    T_est = T.copy()
    T_est[:, :3, 3] += rng.normal(0, 0.01, (n, 3))
    write_tum(d / "traj.txt", t[keep], T_est[keep])
    write_tum(d / "gt.txt", t, T)
    rows = ["frame,time,status,samples,inliers,residual_px,health,ms,score,aid,reason"]
    rows += [f"{k},{t[k]:.6f},{'model' if keep[k] else 'lost'},80,60,0.2,10,3,{0.9 if keep[k] else -0.5},standby,"
             for k in range(n)]
    (d / "traj.csv").write_text("\n".join(rows) + "\n")
    P = rng.uniform([-1, -0.75, 0], [1, 0.75, 1.2], (4000, 3))
    P[:, 2] = np.where(rng.random(4000) < 0.5, 1.2, P[:, 2]) + rng.normal(0, 0.01, 4000)
    write_cloud(d / "cloud.ply", P)
    c2m_args = ["c2m", d / "cloud.ply", d / "box.obj", "--thresholds", "0.01,0.05", "--json", "-q",
                "--plot", d.parent / "cli_hist.png"]
    (d / "c2m.json").write_text(run_mst(*c2m_args).stdout)
    ev_args = ["eval", "traj", d / "traj.txt", d / "gt.txt", "--align", "none", "--json", "-q"]
    (d / "eval.json").write_text(run_mst(*ev_args).stdout)
    # the run log, as samples/demo.sh writes it: the exact command lines, in order, with their stdout file
    (d / "commands.sh").write_text("".join(f"{shlex.join(['mst', *map(str, a)])} > {f}\n"
                                           for a, f in ((c2m_args, "c2m.json"), (ev_args, "eval.json"))))
    return d


def _report(run: Path, out: Path, *args) -> tuple[str, dict]:
    r = run_mst("report", run, "-o", out, "--json", "-q", *args)
    return out.read_text(), json.loads(r.stdout)


def _overlay_args(d: Path) -> list:
    return ["--frames", d / "rgb", "--model", d / "box.obj", "--camera", d / "camera.json", "--fps", "30"]


@pytest.fixture(scope="module")
def report(run_dir) -> tuple[Path, str, dict]:
    out = run_dir.parent / "report.html"
    return (out, *_report(run_dir, out, *_overlay_args(run_dir)))


def test_run_folder_report_sections_and_self_contained(report, run_dir):
    _, html, res = report
    for title in SECTIONS:
        assert title in html, title
    assert res["batch"] is False and res["notes"] == [] and res["images"] >= 4 + 6
    assert "ΔX" in html and "Δψ" in html and "frame 4: lost" in html
    srcs = re.findall(r'src="([^"]*)"', html)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs)
    assert "<script" not in html and not re.search(r"(href|src)=\"(https?:)?//", html)
    assert '"thresholds_m": [\n    0.01,\n    0.05\n  ]' in html  # the c2m configuration, as recorded
    # the commands section: every line of the run log, in order, each stage's config beside it
    from html import escape

    block = html[html.index("Commands (commands.sh, in the order they ran)"):]
    lines = (run_dir / "commands.sh").read_text().splitlines()
    pos = [block.index(escape(line, quote=False)) for line in lines]
    assert len(lines) == 2 and pos == sorted(pos) and "mst c2m " in lines[0]
    assert block.index("c2m configuration") > pos[-1] and "eval configuration" in block
    assert res["config"]["overlay_frames"] == 6
    # the histogram is the image `mst c2m --plot` writes (the same function on the same distances)
    import base64

    hist = re.search(r'alt="C2M histogram" src="data:image/png;base64,([^"]+)"', html).group(1)
    assert base64.b64decode(hist) == (report[0].parent / "cli_hist.png").read_bytes()


def test_report_settings_from_a_config_file_and_unknown_key(run_dir, tmp_path):
    cfg = tmp_path / "report.yaml"
    cfg.write_text("report:\n  overlay_frames: 2\n  c2m_max_points: 0\n")
    html, res = _report(run_dir, tmp_path / "r.html", *_overlay_args(run_dir), "--config", cfg)
    assert len(re.findall(r"<figcaption>frame \d+", html)) == 2 and res["config"]["overlay_frames"] == 2
    cfg.write_text("report:\n  overlay: 2\n")
    r = run_mst("report", run_dir, "-o", tmp_path / "r2.html", "--config", cfg, check=False)
    assert r.returncode == 1 and "overlay: unknown key" in r.stderr and not (tmp_path / "r2.html").exists()


def test_batch_folder_report_and_bad_run_dir(run_dir, tmp_path):
    batch = tmp_path / "batch"
    for name, status in (("a", "ok"), ("b", "failed")):
        shutil.copytree(run_dir, batch / name)
        argv = ["track", str(run_dir / "rgb"), "--model", str(run_dir / "box.obj"), "--camera",
                str(run_dir / "camera.json"), "--init", "p.txt", "-o", "traj.txt", "--fps", "30"]
        entry = {"status": status, "argv": argv, "error": "mst track: error: p.txt: broken" if status == "failed" else None}
        (batch / name / "batch-state.json").write_text(json.dumps({"version": 1, "stages": {"track": entry}}))
    for f in ("c2m.json", "cloud.ply", "eval.json"):  # the failed run wrote nothing after its track
        (batch / "b" / f).unlink()
    html, res = _report(batch, tmp_path / "b.html", "--overlay-frames", "2", "--set", "c2m_max_points=0")
    assert res["batch"] is True and res["runs"] == ["a", "b"] and res["sections"] == ["Batch overview", "a", "b"]
    assert "b: mst track: error: p.txt: broken" in html and "mst track " in html
    assert html.count("<figcaption>frame") == 4  # the overlay strip from each run's recorded track command
    r = run_mst("report", tmp_path / "nope", "-o", tmp_path / "x.html", check=False)
    assert r.returncode == 1 and r.stderr.strip().endswith("run folder does not exist")
    assert not (tmp_path / "x.html").exists()


def test_report_in_headless_chromium(report, tmp_path):
    """The page opens in a real browser: every section rendered, a non-blank screenshot, no console errors."""
    import cv2

    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("chromium is not installed")
    html_path = report[0]
    shot = tmp_path / "shot.png"
    cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--window-size=1300,6000",
           "--enable-logging=stderr", "--v=0", f"--screenshot={shot}", html_path.as_uri()]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert shot.is_file(), r.stderr[-2000:]
    console = [x for x in r.stderr.splitlines() if "CONSOLE" in x or "Failed to load resource" in x
               or "net::ERR" in x or "Uncaught" in x]
    assert console == []
    img = cv2.imread(str(shot))
    assert img is not None and img.std() > 10
    # drawn content down the page: the rows that are not plain white reach beyond the first screen
    busy = np.nonzero((img < 240).any(axis=2).mean(axis=1) > 0.02)[0]
    assert len(busy) > 1000 and busy.max() > 3000
    assert len(np.unique(img.reshape(-1, 3)[::97], axis=0)) > 200
