"""Navigation logs: nav.csv round trip, strict validation (one clear message each), the simulator's error model."""

from __future__ import annotations

import numpy as np
import pytest
from nav_helpers import flight

from mst import InputError
from mst.core.poses import inv_T
from mst.pipeline.init_pose import pose_from_gps
from mst.pipeline.nav.log import (
    NavLog,
    NavSimConfig,
    R_from_ypr_deg,
    format_navlog,
    interpolate_poses,
    mount_T_body_cam,
    read_mount_rotation,
    read_navlog,
    simulate_nav,
    ypr_deg_from_R,
)

HEADER = "t,x,y,z,yaw,pitch,roll\n"


def test_conventions_match_init_from_pose():
    # the body/mount convention is the one of `mst init --from-pose`
    ypr, mount, lever = np.array([30.0, 10.0, -5.0]), (60.0, -20.0, 0.0), (0.1, 0.0, -0.15)
    T_body = np.eye(4)
    T_body[:3, :3] = R_from_ypr_deg(ypr)
    T_body[:3, 3] = [1.0, 2.0, 3.0]
    T_ref = inv_T(pose_from_gps(np.array([1.0, 2.0, 3.0]), *ypr, mount_ypr_deg=mount, mount_offset_m=lever))
    assert np.abs(T_body @ mount_T_body_cam(mount, lever) - T_ref).max() < 1e-12
    a = np.random.default_rng(0).uniform([-180, -80, -180], [180, 80, 180], (50, 3))
    assert np.abs(ypr_deg_from_R(R_from_ypr_deg(a)) - a).max() < 1e-9


def test_round_trip_xyz_and_easting_northing_with_offset(tmp_path):
    rng = np.random.default_rng(0)
    n = 20
    nav = NavLog(t=np.arange(n) * 0.2, p_world=rng.normal(0, 50, (n, 3)), ypr_deg=rng.uniform(-60, 60, (n, 3)),
                 fix=rng.random(n) > 0.2, offset=np.array([389000.0, 5820000.0, 40.0]))
    for enh in (False, True):
        p = tmp_path / f"nav{int(enh)}.csv"
        p.write_text(format_navlog(nav, enh=enh))
        back = read_navlog(p)
        assert np.array_equal(back.fix, nav.fix)
        # written with 4 decimals (0.1 mm, 1e-4 deg)
        assert np.abs(back.p_world[nav.fix] - nav.p_world[nav.fix]).max() < 1e-4
        assert np.abs(back.ypr_deg - nav.ypr_deg).max() < 1e-4
        assert np.allclose(back.offset, nav.offset if enh else 0.0)


@pytest.mark.parametrize("text, problem", [
    (HEADER + "0,0,0,0,0,0,0\n0.2,0,0,0,0,0,0\n0.1,0,0,0,0,0,0\n", "not sorted"),
    (HEADER + "0,0,0,0,0,0,0\n0.2,0,0,0,0,0,0\n0.2,1,0,0,0,0,0\n", "duplicate time 0.2"),
    ("t,x,y,yaw,pitch,roll\n0,0,0,0,0,0\n", "missing column(s) z"),
    ("t,easting,northing,yaw,pitch,roll\n0,0,0,0,0,0\n", "missing column(s)"),
    (HEADER + "0,0,0,0,0,0,0\n0.2,0,nan,0,0,0,0\n", "row 2: column y is NaN"),
    (HEADER + "0,0,0,0,0,0,0\n0.2,0,x,0,0,0,0\n", "row 2: not a number"),
    (HEADER + "0,0,0,0,0,95,0\n", "pitch outside"),
    (HEADER.strip() + ",fix\n0,0,0,0,0,0,0,2\n", "fix must be 0 or 1"),
    (HEADER, "header but no rows"),
    ("# only a comment\n", "empty"),
])
def test_bad_logs_one_clear_message_naming_the_file(tmp_path, text, problem):
    p = tmp_path / "nav.csv"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        read_navlog(p)
    assert str(e.value).startswith(str(p)) and problem in str(e.value), str(e.value)
    assert p.read_text() == text  # input untouched


@pytest.mark.parametrize("text, problem", [
    ("1 0 0\n0 1 0\n0 0 -1\n", "not a rotation"),          # a reflection
    ("1 0.1 0\n0 1 0\n0 0 1\n", "not a rotation"),          # not orthonormal
    ("0 0 0 2\n", "norm 2, not 1"),                          # quaternion
    ("1 0 0 0 1\n", "5 numbers"),
])
def test_mount_rotation_that_is_not_a_rotation(tmp_path, text, problem):
    p = tmp_path / "mount.txt"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        read_mount_rotation(p)
    assert str(e.value).startswith(str(p)) and problem in str(e.value), str(e.value)


def test_mount_rotation_files_accepted(tmp_path):
    R = R_from_ypr_deg(np.array([60.0, -20.0, 5.0]))
    (tmp_path / "r.txt").write_text("# R_body_cam\n" + "\n".join(" ".join(f"{v:.12f}" for v in r) for r in R))
    assert np.abs(read_mount_rotation(tmp_path / "r.txt") - R).max() < 1e-9
    (tmp_path / "q.txt").write_text("0 0 0.7071067811865476 0.7071067811865476\n")
    assert np.abs(read_mount_rotation(tmp_path / "q.txt") - R_from_ypr_deg(np.array([90.0, 0, 0]))).max() < 1e-9


def test_simulator_error_model():
    t, T = flight(duration_s=600.0, fps=5.0)  # 10 minutes: 3000 rows at 5 Hz, enough for the statistics
    cfg = NavSimConfig(seed=4, outlier_rate=0.02, dropouts=2, dropout_s=(5.0, 10.0), ahrs_yaw_bias_deg=2.0,
                       world_yaw_deg=30.0, world_offset_m=(100.0, -50.0, 10.0))
    sim = simulate_nav(t, T, cfg)
    nav = sim.nav
    assert np.allclose(np.diff(nav.t), 1.0 / cfg.rate_hz)
    T_wb = sim.T_world_model @ interpolate_poses(t, T, nav.t) @ inv_T(sim.T_body_cam)
    err = nav.p_world - T_wb[:, :3, 3] - sim.gps_bias_m
    clean = nav.fix & ~sim.outlier
    # white noise std: 3000 samples, relative std of the estimate ~1/sqrt(2N) = 1.3 %: +-10 % is > 7 sigma
    assert np.allclose(err[clean].std(axis=0), [3.0, 3.0, 5.0], rtol=0.10)
    # multipath: 2 % of the rows (binomial sd 0.26 %), 15-40 m off
    assert 0.01 < sim.outlier.mean() < 0.03
    assert (np.linalg.norm(err[sim.outlier], axis=1) > 15.0 - 5 * 5.0).all()
    # the bias is a random walk of 0.05 m/sqrt(s): after 600 s its spread is ~1.2 m per axis, never > 6 sigma
    assert np.abs(sim.gps_bias_m).max() < 6 * 0.05 * np.sqrt(600.0)
    # two dropouts of 5-10 s (they may overlap): between 5 and 20 s without fix
    no_fix_s = (~nav.fix).sum() / cfg.rate_hz
    assert 5.0 <= no_fix_s <= 20.0 + 1e-9
    # AHRS: 3 deg white, +2 deg heading bias (std of the mean 3/sqrt(3000) = 0.05 deg)
    d = nav.ypr_deg - ypr_deg_from_R(T_wb[:, :3, :3])
    d[:, 0] = (d[:, 0] + 180.0) % 360.0 - 180.0
    assert np.allclose(d.mean(axis=0), [2.0, 0.0, 0.0], atol=0.3)
    assert np.allclose(d.std(axis=0), 3.0, rtol=0.10)
    # seeded: the same log twice, another seed another log
    assert np.array_equal(simulate_nav(t, T, cfg).nav.p_world, nav.p_world)
    cfg.seed = 5
    assert not np.array_equal(simulate_nav(t, T, cfg).nav.p_world, nav.p_world)


def test_cli_simulate_writes_log_and_truth_and_rejects_bad_gt(tmp_path, mst):
    from mst.core.trajectory import write_tum

    t, T = flight(duration_s=20.0, fps=10.0)
    write_tum(tmp_path / "gt.txt", t, T)
    r = mst("nav", "simulate", "--gt", tmp_path / "gt.txt", "-o", tmp_path / "nav.csv", "--seed", "3",
            "--enh-offset", "389000", "5820000", "40", "--json")
    import json

    s = json.loads(r.stdout)
    nav = read_navlog(tmp_path / "nav.csv")
    assert s["rows"] == len(nav.t) == 100 and np.allclose(nav.offset, [389000, 5820000, 40])
    assert json.loads((tmp_path / "nav.truth.json").read_text())["mount_ypr_deg"] == [60.0, -20.0, 0.0]
    (tmp_path / "bad.txt").write_text("0 1 2 3\n")
    r = mst("nav", "simulate", "--gt", tmp_path / "bad.txt", "-o", tmp_path / "nav2.csv", check=False)
    assert r.returncode == 1 and "bad.txt" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "nav2.csv").exists()


def test_cli_simulate_settings_from_a_config_file(tmp_path, mst):
    import json

    from mst.core.trajectory import write_tum

    t, T = flight(duration_s=20.0, fps=10.0)
    write_tum(tmp_path / "gt.txt", t, T)
    (tmp_path / "sim.yaml").write_text("rate_hz: 2\ndropouts: 0\n")
    args = ["nav", "simulate", "--gt", tmp_path / "gt.txt", "--config", tmp_path / "sim.yaml", "--json"]
    s = json.loads(mst(*args, "-o", tmp_path / "a.csv").stdout)
    assert s["rows"] == 40 and s["fixes"] == 40 and s["config"]["rate_hz"] == 2.0  # 20 s at 2 Hz, no dropout
    s = json.loads(mst(*args, "--rate", "4", "-o", tmp_path / "b.csv").stdout)  # the option overrides the file
    assert s["rows"] == 80 and s["config"]["rate_hz"] == 4.0
    (tmp_path / "bad.yaml").write_text("rate: 2\n")
    r = mst("nav", "simulate", "--gt", tmp_path / "gt.txt", "--config", tmp_path / "bad.yaml", "-o", tmp_path / "c.csv",
            check=False)
    assert r.returncode == 1 and "rate: unknown key" in r.stderr and not (tmp_path / "c.csv").exists()
