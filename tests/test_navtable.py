"""`mst eval traj --nav`: the UAV table (dX dY dZ d-yaw) of vision, GPS/AHRS and fused against the truth.

Budget: the scene of tests/nav_helpers.py (vision white noise 0.3 m / 0.5 deg per axis), a log without
multipath (so the GPS column's spread is its white noise 3/3/5 m plus a bias walk of ~0.4 m over
60 s; 300 fixes: the std of a std estimate is ~4 %).
"""

from __future__ import annotations

import json

from nav_helpers import VISION_SIGMA_M, flight, noisy_vision

from mst.core.trajectory import write_tum
from mst.eval.traj.navtable import nav_table_from_files
from mst.pipeline.nav.fusion import FusionConfig, fuse_navigation
from mst.pipeline.nav.log import NavSimConfig, simulate_nav, write_sim_outputs


def test_nav_table_columns_match_the_noise_budget(tmp_path, mst):
    t, T = flight()
    t_v, T_v, C_v, keep, _ = noisy_vision(t, T, gap=(20.0, 26.0), seed=4)
    sim = simulate_nav(t, T, NavSimConfig(seed=6, outlier_rate=0.0, world_yaw_deg=30.0, world_offset_m=(100.0, -50.0, 10.0)))
    res = fuse_navigation(t_v, T_v, C_v, sim.nav, FusionConfig(lever_arm_m=sim.config.lever_arm_m, ang_accel_sigma_dps2=0.5))
    write_tum(tmp_path / "gt.txt", t, T)
    write_tum(tmp_path / "traj.txt", t_v, T_v)
    write_tum(tmp_path / "fused.txt", res.t, res.T_model_cam)
    write_sim_outputs(sim, tmp_path / "nav.csv", None)
    (tmp_path / "fused.json").write_text(json.dumps(res.to_json()))
    tab = nav_table_from_files(tmp_path / "fused.txt", tmp_path / "gt.txt", tmp_path / "nav.csv", tmp_path / "fused.json",
                               tmp_path / "traj.txt")
    c = tab.to_json()["columns"]
    assert list(c) == ["vision", "GPS/AHRS", "fused"]
    v, g, f = c["vision"], c["GPS/AHRS"], c["fused"]
    assert v["matched"] == keep.sum() and v["gaps"] == (~keep).sum() and f["gaps"] == 0
    for k in ("dX", "dY", "dZ"):
        assert abs(v[k]["std"] / VISION_SIGMA_M - 1) < 0.1  # 1620 samples: +-10 % is > 5 sigma
        assert f[k]["std"] < v[k]["std"]
    # GPS: 3/3/5 m white (+ the bias walk and the calibration's own error): within -15 %/+25 %
    for k, s in (("dX", 3.0), ("dY", 3.0), ("dZ", 5.0)):
        assert 0.85 * s < g[k]["std"] < 1.25 * s, (k, g[k])
    # heading: the AHRS's 3 deg yaw noise (its pitch/roll noise leaks in through the tilted mount)
    assert 2.5 < g["dyaw"]["std"] < 5.2 and abs(g["dyaw"]["mean"]) < 1.0
    # without the calibration: the model frame is taken as the world frame and the constant yaw
    # offset (model-to-world yaw 30 - mount yaw 60 deg) is removed and reported
    tab2 = nav_table_from_files(tmp_path / "fused.txt", tmp_path / "gt.txt", tmp_path / "nav.csv")
    assert abs(tab2.columns["GPS/AHRS"].yaw_offset_deg - (30.0 - 60.0)) < 2.0
    # the CLI prints it and puts it in the JSON
    r = mst("eval", "traj", tmp_path / "fused.txt", tmp_path / "gt.txt", "--align", "none", "--nav", tmp_path / "nav.csv",
            "--nav-calib", tmp_path / "fused.json", "--nav-vision", tmp_path / "traj.txt", "--json")
    assert json.loads(r.stdout)["nav_table"]["columns"]["GPS/AHRS"]["matched"] == g["matched"]
    assert "UAV table against gt.txt" in r.stderr
    (tmp_path / "bad.json").write_text("{}")
    r = mst("eval", "traj", tmp_path / "fused.txt", tmp_path / "gt.txt", "--nav", tmp_path / "nav.csv",
            "--nav-calib", tmp_path / "bad.json", check=False)
    assert r.returncode == 1 and "bad.json" in r.stderr
