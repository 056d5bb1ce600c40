"""mst eval traj: numbers equal evo's (APE/RPE, association, alignments) to 1e-9; UAV table; gaps."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mst.core.poses import make_T, se3_exp, so3_exp
from mst.core.trajectory import read_trajectory, write_tum
from mst.eval import traj as tj

evo_metrics = pytest.importorskip("evo.core.metrics")
from evo.core import sync  # noqa: E402
from evo.tools import file_interface  # noqa: E402


def _make_pair(tmp_path, scale=1.0, seed=3, n=240):
    """A helix-like reference at 30 Hz and a noisy, transformed (and scaled) estimate with jittered
    timestamps and two tracking gaps."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 30.0
    T = se3_exp(np.stack([5 * np.cos(np.arange(n) / 40), 5 * np.sin(np.arange(n) / 40), 0.02 * np.arange(n),
                          0.3 * np.sin(np.arange(n) / 50), np.full(n, 0.2), np.arange(n) / 40], axis=1))
    noise = se3_exp(rng.normal(0, [0.02, 0.02, 0.02, 0.01, 0.01, 0.01], (n, 6)))
    G = make_T(so3_exp([0.1, -0.2, 0.3]), [1.0, 2.0, 3.0])
    E = G @ T @ noise
    E[:, :3, 3] *= scale
    keep = np.ones(n, bool)
    keep[80:110] = False
    keep[170:174] = False
    ref, est = tmp_path / "gt.txt", tmp_path / "est.txt"
    write_tum(ref, t, T)
    write_tum(est, t[keep] + rng.uniform(-0.004, 0.004, keep.sum()), E[keep])
    return est, ref, keep


def _evo(est, ref, align, delta=1, unit="frames"):
    tr = file_interface.read_tum_trajectory_file(str(ref))
    te = file_interface.read_tum_trajectory_file(str(est))
    tr, te = sync.associate_trajectories(tr, te, max_diff=0.01)
    if align in ("se3", "sim3"):
        te.align(tr, correct_scale=align == "sim3")
    elif align == "first":
        te.align_origin(tr)
    out = {}
    for name, rel in (("ate", evo_metrics.PoseRelation.translation_part),
                      ("rot", evo_metrics.PoseRelation.rotation_angle_deg)):
        m = evo_metrics.APE(rel)
        m.process_data((tr, te))
        out[name] = m.get_all_statistics()
    for name, rel in (("rpe_t", evo_metrics.PoseRelation.translation_part),
                      ("rpe_r", evo_metrics.PoseRelation.rotation_angle_deg)):
        u = evo_metrics.Unit.frames if unit == "frames" else evo_metrics.Unit.meters
        m = evo_metrics.RPE(rel, delta=delta, delta_unit=u)
        m.process_data((tr, te))
        out[name] = m.get_all_statistics()
    out["n"] = tr.num_poses
    return out


KEYS = ("rmse", "mean", "median", "std", "min", "max")


@pytest.mark.parametrize("align", ["none", "se3", "sim3", "first"])
def test_equals_evo(tmp_path, align):
    est, ref, keep = _make_pair(tmp_path, scale=1.3 if align == "sim3" else 1.0)
    s = tj.evaluate_trajectories(est, ref, tj.TrajConfig(align=align, delta_frames=3, delta_m=0.5)).to_json()
    ev = _evo(est, ref, align, delta=3)
    evm = _evo(est, ref, align, delta=0.5, unit="metres")
    assert s["associated"] == ev["n"] == keep.sum()
    for k in KEYS:
        assert s["ate"][k] == pytest.approx(ev["ate"][k], abs=1e-9, rel=0)
        assert s["rotation_error_deg"][k] == pytest.approx(ev["rot"][k], abs=1e-9, rel=0)
        assert s["rpe_frames"]["translation"][k] == pytest.approx(ev["rpe_t"][k], abs=1e-9, rel=0)
        assert s["rpe_frames"]["rotation_deg"][k] == pytest.approx(ev["rpe_r"][k], abs=1e-9, rel=0)
        assert s["rpe_metres"]["translation"][k] == pytest.approx(evm["rpe_t"][k], abs=1e-9, rel=0)
        assert s["rpe_metres"]["rotation_deg"][k] == pytest.approx(evm["rpe_r"][k], abs=1e-9, rel=0)
    if align == "sim3":
        assert s["alignment"]["scale"] == pytest.approx(1 / 1.3, rel=0.01)


def test_association_equals_evo_both_directions():
    rng = np.random.default_rng(1)
    a = np.sort(rng.uniform(0, 10, 300))
    b = np.sort(rng.uniform(0, 10, 500))
    for t_est, t_ref in ((a, b), (b, a)):
        ie, ir = tj.associate(t_est, t_ref, 0.01)
        short_is_est = len(t_est) <= len(t_ref)
        i1, i2 = sync.matching_time_indices(t_est if short_is_est else t_ref, t_ref if short_is_est else t_est, 0.01)
        got = (ie, ir) if short_is_est else (ir, ie)
        np.testing.assert_array_equal(got[0], i1)
        np.testing.assert_array_equal(got[1], i2)
        assert len(i1) > 20


def test_uav_table_gaps_and_yaw(tmp_path):
    n = 100
    t = np.arange(n) / 10.0
    # camera looking horizontally (optical axis = model +X rotated by heading psi), at 50 m height
    psi = np.radians(np.linspace(-170, 170, n))
    R0 = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], float)  # cam z -> model +X, cam y -> model -Z
    Rz = np.stack([np.array([[np.cos(p), -np.sin(p), 0], [np.sin(p), np.cos(p), 0], [0, 0, 1]]) for p in psi])
    T_ref = make_T(Rz @ R0, np.column_stack([np.arange(n), np.zeros(n), np.full(n, 50.0)]))
    off = np.radians(2.5)
    Roff = np.array([[np.cos(off), -np.sin(off), 0], [np.sin(off), np.cos(off), 0], [0, 0, 1]])
    T_est = make_T(Roff @ Rz @ R0, T_ref[:, :3, 3] + [0.1, -0.2, 0.3])
    keep = np.ones(n, bool)
    keep[40:50] = False
    keep[90:] = False
    write_tum(tmp_path / "gt.txt", t, T_ref)
    write_tum(tmp_path / "est.txt", t[keep], T_est[keep])
    np.testing.assert_allclose(tj.camera_yaw_deg(T_ref), np.degrees(psi), atol=1e-9)
    s = tj.evaluate_trajectories(tmp_path / "est.txt", tmp_path / "gt.txt", tj.TrajConfig(align="none", yaw_offset_deg=2.0)).to_json()
    u = s["uav_table"]
    assert (u["dX"]["mean"], u["dY"]["mean"], u["dZ"]["mean"]) == pytest.approx((0.1, -0.2, 0.3), abs=1e-6)
    assert u["dX"]["std"] == pytest.approx(0, abs=1e-6)
    assert u["dyaw"]["mean"] == pytest.approx(0.5, abs=1e-6) and u["dyaw"]["std"] == pytest.approx(0, abs=1e-6)
    g = s["gaps"]
    assert g["missing_reference_poses"] == 20 and g["count"] == 2
    assert [(r["first"], r["last"]) for r in g["ranges"]] == [(40, 49), (90, 99)]
    assert g["ranges"][0]["t_start"] == pytest.approx(4.0)


def test_nadir_yaw_uses_image_up():
    # camera looking straight down (optical axis -Z); image up (-y_cam) points to model +Y -> yaw 90
    R = np.array([[1, 0, 0], [0, -1, 0], [0, 0, -1]], float)
    assert tj.camera_yaw_deg(make_T(R, np.zeros(3))) == pytest.approx(90.0)


def test_kitti_and_csv_formats(tmp_path):
    est, ref, keep = _make_pair(tmp_path)
    tr = read_trajectory(ref)
    t, T = tr.t, tr.T_model_cam
    kitti = tmp_path / "gt.kitti"
    np.savetxt(kitti, T[:, :3, :].reshape(len(T), 12))
    trk = read_trajectory(kitti, fps=30.0)
    tk, Tk = trk.t, trk.T_model_cam
    np.testing.assert_allclose(tk, t, atol=1e-6)  # TUM stores 6 decimals
    np.testing.assert_allclose(Tk, T, atol=1e-8)
    csvp = tmp_path / "gps.csv"
    rows = ["time,east,north,up"] + [f"{a!r},{x!r},{y!r},{z!r}" for a, (x, y, z) in zip(t.tolist(), T[:, :3, 3].tolist())]
    csvp.write_text("\n".join(rows) + "\n")
    s = tj.evaluate_trajectories(est, csvp, tj.TrajConfig(align="se3", csv_columns="t=time,x=east,y=north,z=up")).to_json()
    s_ref = tj.evaluate_trajectories(est, ref, tj.TrajConfig(align="se3")).to_json()
    assert s["ate"]["rmse"] == pytest.approx(s_ref["ate"]["rmse"], abs=1e-6)
    assert s["rotation_error_deg"] is None and s["uav_table"]["dyaw"] is None


def test_cli_json_plot_and_errors(tmp_path, mst):
    est, ref, keep = _make_pair(tmp_path)
    r = mst("eval", "traj", est, ref, "--align", "se3", "--json", "--plot", tmp_path / "p.png")
    s = json.loads(r.stdout)
    ev = _evo(est, ref, "se3")
    assert s["ate"]["rmse"] == pytest.approx(ev["ate"]["rmse"], abs=1e-9)
    assert s["gaps"]["count"] == 2 and s["gaps"]["missing_reference_poses"] == (~keep).sum()
    assert (tmp_path / "p.png").read_bytes()[:4] == b"\x89PNG"
    assert "UAV table" in r.stderr
    far = tmp_path / "far.txt"
    far.write_text("1000 0 0 0 0 0 0 1\n")
    r = mst("eval", "traj", far, ref, check=False)
    assert r.returncode == 1 and "no timestamps match" in r.stderr
    r = mst("eval", "traj", tmp_path / "missing.txt", ref, check=False)
    assert r.returncode == 1 and "does not exist" in r.stderr


def test_config_file_sets_a_setting_options_override_unknown_key_fails(tmp_path, mst):
    """TrajConfig through --config: delta_m from the file changes the RPE pairs; --delta-m overrides
    it; the --json config block repeats the run; an unknown key fails naming it."""
    est, ref, keep = _make_pair(tmp_path)
    base = json.loads(mst("eval", "traj", est, ref, "--json", "-q").stdout)
    cfg = tmp_path / "eval.yaml"
    cfg.write_text("delta_m: 0.25\nalign: sim3\n")
    s = json.loads(mst("eval", "traj", est, ref, "--config", cfg, "--json", "-q").stdout)
    assert s["rpe_metres"]["delta_m"] == 0.25 and s["align"] == "sim3" and s["config"]["delta_m"] == 0.25
    assert s["rpe_metres"]["translation"]["count"] > base["rpe_metres"]["translation"]["count"]
    s2 = json.loads(mst("eval", "traj", est, ref, "--config", cfg, "--delta-m", "1", "--json", "-q").stdout)
    assert s2["rpe_metres"] == base["rpe_metres"] | {"rotation_deg": s2["rpe_metres"]["rotation_deg"],
                                                     "translation": s2["rpe_metres"]["translation"]}
    assert s2["config"]["delta_m"] == 1.0
    again = tmp_path / "again.json"
    again.write_text(json.dumps(s["config"]))
    s3 = json.loads(mst("eval", "traj", est, ref, "--config", again, "--json", "-q").stdout)
    assert s3["ate"] == s["ate"] and s3["rpe_metres"] == s["rpe_metres"]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"delta_mm": 2}))
    r = mst("eval", "traj", est, ref, "--config", bad, check=False)
    assert r.returncode == 1 and "delta_mm" in r.stderr and "unknown key" in r.stderr


def test_duplicate_poses_note_on_stderr_and_in_json(tmp_path, mst):
    est, ref, keep = _make_pair(tmp_path)
    lines = est.read_text().splitlines()
    est.write_text("\n".join([lines[0]] + lines) + "\n")  # the first pose twice
    r = mst("eval", "traj", est, ref, "--json")
    note = f"{est}: 1 identical duplicate pose(s) dropped"
    assert json.loads(r.stdout)["notes"] == [note]
    assert f"mst eval traj: note: {note}" in r.stderr
    r = mst("eval", "traj", est, ref, "--json", "-q")
    assert r.stderr == ""


def test_array_core_equals_the_file_form(tmp_path):
    est, ref, keep = _make_pair(tmp_path)
    e, r = read_trajectory(est), read_trajectory(ref)
    cfg = tj.TrajConfig(align="sim3", delta_m=0.5)
    a = tj.compare_trajectories(e.t, e.T_model_cam, r.t, r.T_model_cam, cfg).to_json()
    b = tj.evaluate_trajectories(est, ref, cfg).to_json()
    assert a["estimate"] == "estimate" and b["estimate"] == str(est)
    for k in ("ate", "rotation_error_deg", "rpe_frames", "rpe_metres", "uav_table", "gaps", "alignment", "config"):
        assert a[k] == b[k], k
