"""``mst nav plot``: the figure of vision, GPS/AHRS and fused trajectories against the truth."""

from __future__ import annotations

import json

import numpy as np
from nav_helpers import flight, noisy_vision

from mst.pipeline.nav.run import format_cov_csv


def test_nav_plot_writes_the_figure_and_refuses_a_bad_log(tmp_path, mst):
    from mst.core.trajectory import write_tum

    t, T = flight(30.0)
    t_v, T_v, C_v, _, _ = noisy_vision(t, T, gap=(10.0, 14.0))
    write_tum(tmp_path / "gt.txt", t, T)
    write_tum(tmp_path / "traj.txt", t_v, T_v)
    (tmp_path / "traj.cov.csv").write_text(format_cov_csv(t_v, C_v))
    mst("nav", "simulate", "--gt", tmp_path / "gt.txt", "-o", tmp_path / "nav.csv", "--seed", "2", "--dropouts", "1")
    mst("nav", "fuse", "--traj", tmp_path / "traj.txt", "--nav", tmp_path / "nav.csv", "-o", tmp_path / "fused.txt",
        "--json")
    png = tmp_path / "nav.png"
    r = mst("nav", "plot", "--fused", tmp_path / "fused.txt", "--gt", tmp_path / "gt.txt", "--nav", tmp_path / "nav.csv",
            "--calib", tmp_path / "fused.json", "--vision", tmp_path / "traj.txt", "-o", png, "--json")
    s = json.loads(r.stdout)
    assert list(s["columns"]) == ["vision", "GPS/AHRS", "fused"]
    import cv2

    img = cv2.imread(str(png))
    assert img is not None and img.shape[0] > 500 and img.shape[1] > 800
    # the red vision-gap shading (10-14 s of a 30 s flight) is drawn: light red pixels in every panel
    red = (img[:, :, 2] > 240) & (img[:, :, 1] > 190) & (img[:, :, 1] < 215) & (img[:, :, 0] > 190) & (img[:, :, 0] < 215)
    assert red.sum() > 1000
    bad = tmp_path / "bad.csv"
    bad.write_text((tmp_path / "nav.csv").read_text().replace(",1\n", ",nan\n", 1))
    out2 = tmp_path / "n2.png"
    r = mst("nav", "plot", "--fused", tmp_path / "fused.txt", "--gt", tmp_path / "gt.txt", "--nav", bad, "-o", out2,
            check=False)
    assert r.returncode == 1 and "bad.csv" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not out2.exists()
    assert np.isfinite(s["columns"]["fused"]["ate_rmse_m"])
