"""A smooth ground-truth flight and a noisy "vision" trajectory for the navigation tests (no rendering)."""

from __future__ import annotations

import numpy as np

from mst.core.poses import look_at, so3_exp

#: vision noise budget of the tests: white, per axis (a building tracked from ~70 m: the tracker's
#: depth error at 640 px is a few decimetres, its rotation error a few tenths of a degree)
VISION_SIGMA_M = 0.3
VISION_SIGMA_DEG = 0.5


def flight(duration_s: float = 60.0, fps: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """A UAV orbit: radius 60 m x 42 m, 6 m/s, height 40 +- 3 m, camera looking at a point near the
    model origin (pitch about -30 deg). Max acceleration ~0.6 m/s^2, angular rate ~6 deg/s.
    Returns t (N,) s and T_model_cam (N, 4, 4)."""
    t = np.arange(0.0, duration_s, 1.0 / fps)
    w = 6.0 / 60.0
    P = np.stack([60 * np.cos(w * t), 42 * np.sin(w * t), 40 + 3 * np.sin(0.2 * t)], 1)
    target = np.stack([5 * np.sin(0.1 * t), np.zeros_like(t), np.zeros_like(t)], 1)
    T = np.stack([look_at(p, q) for p, q in zip(P, target)])
    return t, T


def noisy_vision(t: np.ndarray, T: np.ndarray, seed: int = 1, gap: tuple[float, float] | None = (20.0, 26.0)):
    """Ground truth + white noise drawn from the 6x6 covariance C (VISION_SIGMA_*), frames inside
    ``gap`` removed (tracking lost). Returns t_v, T_v, cov_v (K, 6, 6), keep (N,) bool, errors (N, 6)."""
    rng = np.random.default_rng(seed)
    C = np.diag([VISION_SIGMA_M**2] * 3 + [np.radians(VISION_SIGMA_DEG) ** 2] * 3)
    e = rng.normal(size=(len(t), 6)) @ np.linalg.cholesky(C).T
    Tv = T.copy()
    Tv[:, :3, 3] += e[:, :3]
    Tv[:, :3, :3] = so3_exp(e[:, 3:]) @ T[:, :3, :3]
    keep = np.ones(len(t), bool)
    if gap is not None:
        keep[(t >= gap[0]) & (t < gap[1])] = False
    return t[keep], Tv[keep], np.tile(C, (int(keep.sum()), 1, 1)), keep, e


#: the georeference of the tracked nav tests: model -> world, a 30 deg turn about z and an offset (m)
M2W = np.array([[np.cos(np.radians(30)), -np.sin(np.radians(30)), 0, 100.0],
                [np.sin(np.radians(30)), np.cos(np.radians(30)), 0, -50.0], [0, 0, 1, 10.0], [0, 0, 0, 1.0]])


def tracked_sequence(tmp_path_factory, tag: str, scenario: str, fps: float, track_cfg, **synth):
    """``mst synth <scenario>`` of the bundled sample model (320x240, 4x AA, 512 px texture, with depth,
    ``synth`` the other SynthConfig fields) tracked by ``run_track`` with ``track_cfg`` at ``fps``:
    the sequence folder (``traj.txt`` in it). Skips when the sample model is missing."""
    import pytest

    from mst.eval.bench.slam import SAMPLE_MODEL
    from mst.pipeline.synth import SynthConfig, synthesize
    from mst.pipeline.tracking import run_track

    if not SAMPLE_MODEL.exists():
        pytest.skip("samples/building_tin.obj missing")
    out = tmp_path_factory.mktemp(tag) / scenario
    synthesize(scenario, SAMPLE_MODEL, out, SynthConfig(width=320, height=240, fps=fps, aa_samples=4,
                                                        texture_size=512, **synth))
    run_track(out / "rgb", out / "model.obj", out / "camera.json", out / "cMo" / "000000.txt", out / "traj.txt",
              track_cfg, depth_dir=out / "depth", fps=fps)
    return out
