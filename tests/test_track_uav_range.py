"""Issue 11, long range: the 0.1 %-of-distance target at 250 m above the ground (about 300 m from the
buildings) over the real Rotterdam CityJSON set, at the resolution that reaches it.

At 640x480 (fx 525 px) one pixel at 300 m is 0.57 m and the target, 0.30 m, is half a pixel: the
steady flight's ATE there is 1.32 m (0.44 %) against a pose covariance of 0.99 m RMS, i.e. the
image's information, not a defect of the fit; more samples (2 px steps, no cap, no LOD) shrink the
covariance to 0.70 m but raise the error to 1.7-2.5 m (the added samples lie on short, close
edges). At 1280x720 (fx 1050 px: 0.29 m a pixel) the default reaches the target (measured 0.28 m,
0.094 %). Slow: a 240-frame 1280x720 ``mst synth uav`` (the steady flight is its first 20 %).
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
from test_track_uav import _cli, _prepare, _rms, _view_distance


@pytest.mark.slow
def test_250m_band_default_mode_within_0p1_percent_at_1280x720(shared_data, tmp_path):
    from mst.core.trajectory import read_tum
    from mst.meshtools.formats import load_model
    from mst.pipeline.tracking import TrackConfig, run_track

    seq = tmp_path / "seq"
    _cli("synth", "uav", "--model", shared_data / "cityjson/rotterdam_subset.json", "-o", seq, "--frames", 240,
         "--distance", 250, "--width", 1280, "--height", 720, "--no-depth", "--aa", 4, "--texture-size", 512, "-q")
    m = _prepare(seq, tmp_path)
    n_steady = 48  # before the hover and the turn (20 % of 240): straight flight, the block in view
    tg, Tg = read_tum(seq / "gt.txt")
    cam = json.loads((seq / "camera.json").read_text())
    dist = _view_distance(Tg, load_model(m).vertices, cam, range(n_steady))
    res = {}
    for slam in ("auto", "off"):
        out = tmp_path / f"traj_{slam}.txt"
        s = run_track(seq / "rgb", m, seq / "camera.json", tmp_path / "p0.txt", out, TrackConfig(aid=slam), fps=30,
                      frames=f"0:{n_steady}")
        te, Te = read_tum(out)
        idx = np.searchsorted(np.round(tg, 6), np.round(te, 6))
        err = np.linalg.norm(Te[:, :3, 3] - Tg[idx, :3, 3], axis=1)
        rows = list(csv.DictReader(open(out.with_suffix(".cov.csv"))))
        cov = np.array([[float(r[f"c{i}{j}"]) for i in range(6) for j in range(6)] for r in rows if r["status"] == "model"])
        res[slam] = (s, err, cov.reshape(-1, 6, 6))
    s, err, cov = res["auto"]
    ate = _rms(err)
    # the position sigma of the reported 6x6 covariance (camera centre: R^T C_vv R, same trace)
    sig = float(np.sqrt(np.mean(np.trace(cov[:, :3, :3], axis1=1, axis2=2))))
    print(f"250 m at 1280x720: distance {dist:.0f} m, default ATE {ate:.3f} m ({100 * ate / dist:.3f} %, target 0.1 %), "
          f"covariance sigma {sig:.3f} m; edges only ATE {_rms(res['off'][1]):.3f} m")
    # every steady frame tracked by the model, the 6x6 covariance reported for each (symmetric, PSD)
    assert s["tracked"] == n_steady and dict(s["status_counts"]).get("model") == n_steady
    assert len(cov) == n_steady and np.allclose(cov, cov.transpose(0, 2, 1), rtol=1e-5, atol=1e-15)
    assert (np.linalg.eigvalsh(0.5 * (cov + cov.transpose(0, 2, 1))) > -1e-12).all()
    # the target: ATE <= 0.1 % of the camera-building distance
    assert ate <= 1e-3 * dist, (ate, dist)
    # and the error is what the covariance says (5 sigma RMS, as test_track_uav): no hidden bias
    assert ate <= 5.0 * sig, (ate, sig)
    # the default is as accurate as edges only (1 sigma of the comparison = 0.2 x the 5-sigma budget)
    assert ate <= _rms(res["off"][1]) + sig, (ate, _rms(res["off"][1]))
