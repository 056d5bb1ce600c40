"""Agreement with ViSP 3.5's own model-based tracker on the real tea-box video (issue #12).

The anchor is ViSP's runner (``../shared/tools/visp-anchor``, built by its ``build.sh`` into
/tmp/visp_build, or ``$VISP_ANCHOR``); the test skips when it is not built or the data is absent.
Both trackers start from the same initial pose (mst's PnP of the clicked points, handed to the
runner as a 4x4 cMo) and read the same settings (teabox.xml). Per frame the error is the mean
distance (px) of the 8 box corners projected with the two poses.

Budget: there is no ground truth; the reference for "agrees" is ViSP's own spread, the distance
between its edge tracker and its hybrid (edges + KLT) tracker on the same frames (measured 0.89 px
mean). A pose that agrees with ViSP's hybrid tracker within that spread (x1.5, and its worst frame
within ViSP's worst + 1 px, the pixel size) is as good as ViSP can tell; the default mode must
agree at least as well as ``--slam off`` (paired per-frame difference <= 2 standard errors).

Measured (session 6): ViSP's own spread 0.894 px; ``--slam off`` 0.739 px from ViSP's hybrid, the
default (edges + KLT) 0.768 px, paired difference +0.029 px against its 2-SE bound 0.043. Before the
KLT information cap (``edges.klt_info_cap``, :func:`mst.pipeline.tracking.vvs.klt_info_scale`) the
default was 0.793 px (+0.054 against 0.051, a strict xfail): its ~200 KLT points outweighed the
edges 5x, and the pose followed their drift (0.1-0.4 px farther from ViSP's hybrid on frames 19-35,
the points' 17th-25th frame and the re-detection on the drifted pose).
"""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from mst.core.poses import inv_T
from mst.core.trajectory import read_tum, write_pose_file


def _runner() -> Path:
    exe = Path(os.environ.get("VISP_ANCHOR", "/tmp/visp_build/visp_mbt_anchor"))
    if not exe.is_file():
        pytest.skip("ViSP runner not built (../shared/tools/visp-anchor/build.sh)")
    return exe


@pytest.fixture(scope="module")
def teabox(shared_data, tmp_path_factory):
    from mst.core.camera import read_camera
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.init_pose import init_from_clicks, read_clicks

    exe = _runner()
    t = shared_data / "visp-teabox"
    d = tmp_path_factory.mktemp("teabox_visp")
    cam = read_camera(t / "teabox.xml")
    X, uv = read_clicks(t / "teabox.clicks", t / "teabox.init")
    T0 = init_from_clicks(X, uv, cam.K).T_cam_model
    write_pose_file(d / "p0.txt", T0)
    np.savetxt(d / "cMo0.txt", T0)
    V = np.asarray(load_tracking_model(t / "teabox.cao").vertices, float)
    K = cam.K

    def corners(T_cam_model):  # (n, 8, 2) px
        Xc = np.einsum("nij,kj->nki", T_cam_model[:, :3, :3], V) + T_cam_model[:, None, :3, 3]
        return Xc[..., :2] / Xc[..., 2:3] * [K[0, 0], K[1, 1]] + K[:2, 2]

    visp = {}
    for mode in ("edge", "hybrid"):
        out = d / f"visp_{mode}.txt"
        subprocess.run([str(exe), "--mode", mode, "--model", str(t / "teabox.cao"), "--input", str(t / "teabox.mp4"),
                        "--cam", *(f"{v:.5f}" for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2])),
                        "--init-pose", str(d / "cMo0.txt"), "--out", str(out)],
                       check=True, capture_output=True, timeout=120)
        a = np.loadtxt(out, comments="#", ndmin=2)
        T = np.tile(np.eye(4), (len(a), 1, 1))
        T[:, :3, :] = a[:, 1:13].reshape(-1, 3, 4)
        visp[mode] = corners(T)
    return t, d, corners, visp


def _mst(t, d, aid, corners):
    from mst.pipeline.tracking import run_track
    from mst.pipeline.tracking.config import read_tracker_xml

    cfg = read_tracker_xml(t / "teabox.xml").replace(aid=aid)  # what `mst track` reads from the camera file
    s = run_track(t / "teabox.mp4", t / "teabox.cao", t / "teabox.xml", d / "p0.txt", d / f"mst_{aid}.txt", cfg)
    _, P = read_tum(d / f"mst_{aid}.txt")
    return s, corners(inv_T(P))


def test_default_agrees_with_visp_hybrid(teabox):
    t, d, corners, visp = teabox
    n = len(visp["hybrid"])
    spread = np.linalg.norm(visp["edge"] - visp["hybrid"], axis=2).mean(1)  # ViSP's own edge vs hybrid, px
    s_def, c_def = _mst(t, d, "auto", corners)
    s_off, c_off = _mst(t, d, "off", corners)
    assert len(c_def) == len(c_off) == n and s_def["model"] == n  # every frame tracked, all `model`
    e_def = np.linalg.norm(c_def - visp["hybrid"], axis=2).mean(1)
    e_off = np.linalg.norm(c_off - visp["hybrid"], axis=2).mean(1)
    # as close to ViSP's hybrid tracker as ViSP's own edge tracker is (x1.5), worst frame within
    # ViSP's worst + the pixel size
    assert e_def.mean() <= 1.5 * spread.mean(), (e_def.mean(), spread.mean())
    assert e_def.max() <= spread.max() + 1.0, (e_def.max(), spread.max())
    # the default agrees at least as well as edges only (paired difference <= 2 standard errors)
    diff = e_def - e_off
    assert diff.mean() <= 2.0 * diff.std(ddof=1) / np.sqrt(n), (e_def.mean(), e_off.mean())
