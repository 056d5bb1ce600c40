"""``mst nav fuse`` on a TRACKED sequence: ``mst track`` output (traj.txt with its per-frame
traj.csv and traj.cov.csv beside it), not simulated vision.

``mst synth orbit`` of the sample house at 320x240, 40 frames at 2 fps (20 s, ~22 m of ground),
tracked with the RGB-D aid; a GPS/AHRS log simulated from the truth (3 m / 5 m GPS, 3 deg AHRS with
a 2 deg heading bias, 60 deg mount, lever 0.18 m) and the model georeferenced (the model-to-world
transform given: 22 m of ground do not fix its yaw from 3 m GPS). Until this test, nav fuse refused
every mst track output: it read the tracker's traj.cov.csv (per frame, twist covariance of
T_cam_model) as its own format ("missing column(s) t").
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from nav_helpers import tracked_sequence

FPS = 2.0


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    from mst.pipeline.tracking import TrackConfig

    return tracked_sequence(tmp_path_factory, "navtrack", "orbit", FPS, TrackConfig(aid="rgbd"), frames=40)


def test_nav_fuse_reads_mst_track_output_and_keeps_its_accuracy(tracked, tmp_path, mst):
    from mst.core.trajectory import read_tum
    from mst.pipeline.nav.run import read_cov_csv

    seq = tracked
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    np.savetxt(tmp_path / "m2w.txt", [[c, -s, 0, 100], [s, c, 0, -50], [0, 0, 1, 10], [0, 0, 0, 1]])
    mst("nav", "simulate", "--gt", seq / "gt.txt", "-o", tmp_path / "nav.csv", "--seed", "1", "--world-yaw", "30",
        "--world-offset", "100", "-50", "10")
    truth = json.loads((tmp_path / "nav.truth.json").read_text())
    r = mst("nav", "fuse", "--traj", seq / "traj.txt", "--nav", tmp_path / "nav.csv", "-o", tmp_path / "fused.txt",
            "--lever", "0.1", "0", "-0.15", "--model-to-world", tmp_path / "m2w.txt", "--json")
    summ = json.loads(r.stdout)
    _, T_gt = read_tum(seq / "gt.txt")
    t_v, T_v = read_tum(seq / "traj.txt")
    t_f, T_f = read_tum(tmp_path / "fused.txt")
    _, C_f = read_cov_csv(tmp_path / "fused.cov.csv")
    e_v = np.linalg.norm(T_v[:, :3, 3] - T_gt[np.rint(t_v * FPS).astype(int), :3, 3], axis=1)
    e_f = np.linalg.norm(T_f[:, :3, 3] - T_gt[np.rint(t_f * FPS).astype(int), :3, 3], axis=1)
    rms_v, rms_f = np.sqrt(np.mean(e_v**2)), np.sqrt(np.mean(e_f**2))
    # the vision (~1 cm at 15 m) is 300x better than the GPS: the fusion must keep it (the tracker's
    # covariances are used, not the 5 cm default), within 1.25x
    assert len(t_f) == 40 and rms_f <= 1.25 * rms_v, (rms_f, rms_v)
    # the tracker's covariances, carried through, predict the fused error (within 2x either way)
    pred = np.sqrt(np.mean(np.trace(C_f[:, :3, :3], axis1=1, axis2=2)))
    assert 0.5 * pred <= rms_f <= 2 * pred, (rms_f, pred)
    # the mount the log can show (the heading bias folded in): 100 AHRS rows (5 Hz) of 3 deg per axis,
    # the mean's std 0.3 deg; within 1.2 deg (4 std) per angle
    d = np.array(summ["mount_ypr_deg"]) - truth["effective_mount_ypr_deg"]
    assert np.abs((d + 180) % 360 - 180).max() <= 1.2, (summ["mount_ypr_deg"], truth["effective_mount_ypr_deg"])


def test_track_cov_without_its_frame_times_is_refused(tracked, tmp_path, mst):
    import shutil

    shutil.copy(tracked / "traj.txt", tmp_path / "traj.txt")
    shutil.copy(tracked / "traj.cov.csv", tmp_path / "traj.cov.csv")  # no traj.csv beside it
    mst("nav", "simulate", "--gt", tracked / "gt.txt", "-o", tmp_path / "nav.csv")
    r = mst("nav", "fuse", "--traj", tmp_path / "traj.txt", "--nav", tmp_path / "nav.csv", "-o", tmp_path / "f.txt",
            check=False)
    assert r.returncode == 1 and "traj.cov.csv" in r.stderr and "traj.csv" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not (tmp_path / "f.txt").exists()
