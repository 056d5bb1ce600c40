"""``mst refine`` on a deliberately degraded trajectory: the RGB-D SLAM aid run from noisy clicks
on a ``mst synth corridor`` sequence with depth (320x240; the model leaves the view for ~45
frames, so the aid carries a pose biased by the bad start through the gap).

The issue's bounds: the refinement lowers the ATE and the mean cloud-to-model distance of the
fused model samples by >= 30 % each. The C2M check is independent of refine's own statistics:
the samples that belong to the model are chosen with the ground-truth poses (within 2 cm of the
model: the depth is exact float metres, the surface is ray cast), then placed with the tracked and
the refined poses and measured against the mesh.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from mst.eval.bench.slam import SAMPLE_MODEL

FPS = 30.0


def _degraded(out, seed: int, frames: int = 90):
    """The corridor rendered, the first pose from 4 clicks with 5 px noise (forced: the init's own
    residual check would refuse them), tracked by the RGB-D aid -> (sequence folder, traj.txt)."""
    from mst.pipeline.init_pose import InitConfig, run_init
    from mst.pipeline.synth import SynthConfig, synthesize
    from mst.pipeline.tracking import TrackConfig, run_track

    synthesize("corridor", SAMPLE_MODEL, out, SynthConfig(width=320, height=240, frames=frames, click_noise=5.0,
                                                           n_clicks=4, seed=seed, aa_samples=4, texture_size=512))
    run_init(out / "model.obj", out / "camera.json", out / "pose0.txt", clicks_path=out / "clicks.txt",
             cfg=InitConfig(max_residual_px=100.0))
    from mst.pipeline.slam.config import SlamConfig

    # the error budget (1 % / 2 deg) would refuse most of these biased poses (2 sigma 1.2-2.7 % at
    # 320x240, several % off): a degraded trajectory to refine is asked for with it widened to 10 %,
    # as a user keeping every pose for `mst refine` would
    run_track(out / "rgb", out / "model.obj", out / "camera.json", out / "pose0.txt", out / "traj.txt",
              TrackConfig(aid="rgbd", slam=SlamConfig(drift_budget_rel=0.10)), depth_dir=out / "depth", fps=FPS)
    return out, out / "traj.txt"


@pytest.fixture(scope="module")
def degraded(tmp_path_factory):
    if not SAMPLE_MODEL.exists():
        pytest.skip("samples/building_tin.obj missing")
    return _degraded(tmp_path_factory.mktemp("refine") / "corridor", seed=0)


def _model_sample_c2m(seq, traj, step: int = 4, every: int = 5) -> float:
    """Mean distance (m) to the model of the depth samples that lie on the model at the true pose,
    placed with the poses of ``traj`` (every ``every``-th frame)."""
    from mst.core.camera import read_camera
    from mst.core.poses import transform_points
    from mst.core.trajectory import read_tum
    from mst.meshtools.formats import load_triangles
    from mst.pipeline.depth_io import list_depth_frames, read_depth
    from mst.pipeline.refine.geometry import ModelSurface, backproject

    V, F = load_triangles(seq / "model.obj")
    surf = ModelSurface(V, F, 1000, 0)
    cam = read_camera(seq / "camera.json")
    files = list_depth_frames(seq / "depth")
    t, T = read_tum(traj)
    _, T_gt = read_tum(seq / "gt.txt")
    k = np.rint(t * FPS).astype(int)
    d = []
    for i in range(0, len(t), every):
        P, _ = backproject(read_depth(files[k[i]]), cam, step, 0.1, 100.0)
        on_model = surf.distance(transform_points(T_gt[k[i]], P)) < 0.02
        d.append(surf.distance(transform_points(T[i], P[on_model])))
    return float(np.concatenate(d).mean())


def test_refine_lowers_ate_and_c2m_by_30_percent(degraded, tmp_path, mst):
    seq, traj = degraded
    out = tmp_path / "refined.txt"
    r = mst("refine", "--traj", traj, "--model", seq / "model.obj", "--camera", seq / "camera.json", "--depth",
            seq / "depth", "--fps", FPS, "--gt", seq / "gt.txt", "-o", out, "--json")
    s = json.loads(r.stdout)
    from mst.core.trajectory import read_tum

    t0, _ = read_tum(traj)
    t1, _ = read_tum(out)
    np.testing.assert_array_equal(t0, t1)  # same times, every pose
    # the degradation is real: the start is off by several % of the ~15 m distance
    assert s["ate"]["before_m"] > 0.05
    assert s["ate"]["after_m"] <= 0.7 * s["ate"]["before_m"]
    assert s["c2m_after"]["mean_m"] <= 0.7 * s["c2m_before"]["mean_m"]
    c_before, c_after = _model_sample_c2m(seq, traj), _model_sample_c2m(seq, out)
    assert c_after <= 0.7 * c_before
    assert s["config"]["fps"] == FPS and s["priors"] >= 2


def test_refine_bundle_adjustment_with_klt_tie_points(degraded, tmp_path, mst):
    """--frames: the keyframes are bundle adjusted first (KLT tie points, the tracked poses as
    priors). The degradation is a global bias of the start, which tie points cannot see: the BA
    alone must not spoil the ATE (within 5 %), tightens the tie points to the KLT's precision
    (reprojection RMS <= 1.5 x the 1 px sigma, below the start's), and the whole refinement still
    meets the issue's -30 % on ATE and C2M."""
    seq, traj = degraded
    out = tmp_path / "refined.txt"
    r = mst("refine", "--traj", traj, "--model", seq / "model.obj", "--camera", seq / "camera.json", "--depth",
            seq / "depth", "--frames", seq / "rgb", "--fps", FPS, "--gt", seq / "gt.txt", "-o", out, "--json")
    s = json.loads(r.stdout)
    ba = s["ba"]
    assert ba["points"] >= 100 and ba["priors_from_tracker"] >= 2, ba
    assert ba["reproj_rms_after_px"] <= min(1.5, ba["reproj_rms_before_px"]), ba
    assert s["ate"]["after_ba_m"] <= 1.05 * s["ate"]["before_m"], s["ate"]
    assert s["ate"]["after_m"] <= 0.7 * s["ate"]["before_m"], s["ate"]
    assert _model_sample_c2m(seq, out) <= 0.7 * _model_sample_c2m(seq, traj)
    r = mst("refine", "--traj", traj, "--model", seq / "model.obj", "--camera", seq / "camera.json", "--depth",
            seq / "depth", "--nav", seq / "gt.txt", "--fps", FPS, "-o", tmp_path / "n.txt", check=False)
    assert r.returncode == 1 and "--frames" in r.stderr and not (tmp_path / "n.txt").exists()


def test_refine_keeps_a_correct_trajectory(degraded, tmp_path):
    """The ground truth in: ICP on exact depth must leave it where it is. Budget: a 320x240 pixel
    is ~6 cm at 15 m, ~250 model samples per keyframe on 2-4 planes -> mm-level plane fits; 1 cm
    (0.07 % of the distance) is a wide margin and far below the degraded run's 5 %."""
    from mst.pipeline.refine import RefineConfig, refine

    seq, _ = degraded
    s = refine(seq / "gt.txt", seq / "model.obj", seq / "camera.json", seq / "depth", tmp_path / "r.txt",
               RefineConfig(fps=FPS), gt_path=seq / "gt.txt")
    assert s.ate["before_m"] == 0.0
    assert s.ate["after_m"] < 0.01
    assert s.c2m_after.mean_m <= s.c2m_before.mean_m


def test_refine_bad_input_one_line_no_output(degraded, tmp_path, mst):
    seq, traj = degraded
    out = tmp_path / "r.txt"
    base = ["refine", "--model", seq / "model.obj", "--camera", seq / "camera.json", "--depth", seq / "depth", "-o", out]
    r = mst(*base, "--traj", traj, check=False)  # times in seconds without --fps
    assert r.returncode == 1 and "needs the fps" in r.stderr and str(traj) in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and not out.exists()
    r = mst(*base, "--traj", traj, "--fps", "1000", check=False)  # poses past the last depth frame
    assert r.returncode == 1 and "point past the last of 90 depth frames" in r.stderr and not out.exists()
    r = mst(*base, "--traj", traj, "--fps", FPS, "--set", "icp_max_rel=[0.1,-1,0.02]", check=False)
    assert r.returncode == 1 and "icp_max_rel" in r.stderr and not out.exists()
    cam = json.loads((seq / "camera.json").read_text())  # a camera for other images than the depth's
    cam.update(width=cam["width"] * 2, height=cam["height"] * 2)
    (tmp_path / "cam2.json").write_text(json.dumps(cam))
    r = mst("refine", "--model", seq / "model.obj", "--camera", tmp_path / "cam2.json", "--depth", seq / "depth", "-o",
            out, "--traj", traj, "--fps", FPS, check=False)
    assert r.returncode == 1 and "registered to the tracked camera" in r.stderr and not out.exists()


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_refine_seeds(tmp_path, seed):
    from mst.pipeline.refine import RefineConfig, refine

    seq, traj = _degraded(tmp_path / "corridor", seed)
    s = refine(traj, seq / "model.obj", seq / "camera.json", seq / "depth", tmp_path / "r.txt", RefineConfig(fps=FPS),
               gt_path=seq / "gt.txt")
    assert s.ate["after_m"] <= 0.7 * s.ate["before_m"]
    assert _model_sample_c2m(seq, tmp_path / "r.txt") <= 0.7 * _model_sample_c2m(seq, traj)
