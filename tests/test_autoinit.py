"""Automatic initialisation (`mst init --from-nav`): search around a GPS/AHRS guess, refine, or refuse.

Budget: an L-shaped building (12 x 8 x 6 m) seen from 40 m with a 640x480, f = 500 px camera (the
building spans ~150 px); guesses drawn with the nav noise (3/3/5 m, 3 deg per axis); converged means
within 0.5 % of the distance (0.2 m) and 0.5 deg -- the edge tracker itself reaches ~0.1 %.
A guess that does not converge must be refused, never returned (silent wrong output).
"""

from __future__ import annotations

import numpy as np
import pytest
from synth_helpers import render_views

from mst.core.camera import Camera
from mst.core.poses import inv_T, look_at, pose_error, so3_exp
from mst.pipeline.autoinit import AutoInitConfig, auto_init

DIST = 40.0


@pytest.fixture(scope="module")
def view():
    import cv2

    from mst.meshtools.generate import l_shape_model

    m = l_shape_model()
    cam = Camera(500, 500, 319.5, 239.5, 640, 480)
    c = m.vertices.mean(0)
    T_mc = look_at(c + DIST * np.array([np.cos(0.6), -np.sin(0.6), 0.5]) / np.linalg.norm([1, 0.5]) * 1.0, c)
    img = render_views(m, cam, [inv_T(T_mc)], seed=0)[0]
    return m, cam, T_mc, img, cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


def _guess(T_mc, rng):
    G = T_mc.copy()
    G[:3, 3] += rng.normal(0, [3.0, 3.0, 5.0])
    G[:3, :3] = so3_exp(np.radians(rng.normal(0, 3.0, 3))) @ G[:3, :3]
    return G


def _trials(view, n, seed):
    """(converged, accepted but wrong) over n seeded guesses."""
    m, cam, T_mc, _, gray = view
    rng = np.random.default_rng(seed)
    dist = np.linalg.norm(T_mc[:3, 3] - m.vertices.mean(0))
    good = wrong = 0
    for i in range(n):
        r = auto_init(gray, m, cam, inv_T(_guess(T_mc, rng)), AutoInitConfig(seed=i))
        if r.ok:
            dt, dr = pose_error(inv_T(r.T_cam_model), T_mc)
            ok = bool(dt <= 0.005 * dist and dr <= 0.5)
            good += ok
            wrong += not ok
    return good, wrong


@pytest.mark.slow
@pytest.mark.timeout(3600)  # 100 searches of ~0.7 s CPU; minutes of wall on a loaded machine
def test_converges_in_95_of_100_trials(view):
    # measured 2026-12-02: 100 of 100, none wrong (0.70 s CPU median per search, load ~5)
    good, wrong = _trials(view, 100, seed=1)
    assert good >= 95 and wrong == 0, (good, wrong)


@pytest.mark.slow
def test_refuses_a_texture_full_of_edges(view):
    import cv2

    m, cam, T_mc, _, gray = view
    rng = np.random.default_rng(3)
    # every pose scores alike -> ambiguous, refused
    tex = cv2.GaussianBlur(rng.normal(128, 60, gray.shape).astype(np.float32), (0, 0), 3)
    tex = np.clip((tex - 128) * 4 + 128, 0, 255).astype(np.uint8)
    r = auto_init(tex, m, cam, inv_T(T_mc))
    assert not r.ok and r.T_cam_model is None, r.reason


def test_cli_from_nav_converges_or_refuses_a_frame_without_the_model(view, tmp_path, mst):
    import cv2

    from mst.core.camera import write_camera
    from mst.core.trajectory import read_pose_file
    from mst.meshtools.formats import save_model
    from mst.pipeline.nav.log import R_MOUNT_CAM, NavLog, format_navlog, ypr_deg_from_R

    m, cam, T_mc, img, _ = view
    save_model(tmp_path / "model.obj", m)
    write_camera(tmp_path / "camera.json", cam)
    cv2.imwrite(str(tmp_path / "f0.png"), img)
    cv2.imwrite(str(tmp_path / "blank.png"), np.full_like(img, 128))
    # a log row from a noisy guess of the platform (mount 0: body x = optical axis)
    G = _guess(T_mc, np.random.default_rng(5))
    ypr = ypr_deg_from_R(G[:3, :3] @ R_MOUNT_CAM.T)
    nav = NavLog(t=np.array([0.0, 0.2]), p_world=np.tile(G[:3, 3], (2, 1)), ypr_deg=np.tile(ypr, (2, 1)), fix=np.ones(2, bool))
    (tmp_path / "nav.csv").write_text(format_navlog(nav))
    args = ["init", "--model", tmp_path / "model.obj", "--camera", tmp_path / "camera.json", "--from-nav", tmp_path / "nav.csv"]
    mst(*args, "--image", tmp_path / "f0.png", "-o", tmp_path / "pose0.txt")
    dt, dr = pose_error(inv_T(read_pose_file(tmp_path / "pose0.txt")), T_mc)
    assert dt <= 0.005 * DIST and dr <= 0.5
    r = mst(*args, "--image", tmp_path / "blank.png", "-o", tmp_path / "pose1.txt", check=False)
    assert r.returncode == 1 and "blank.png" in r.stderr and "may not show the model" in r.stderr
    assert not (tmp_path / "pose1.txt").exists()


@pytest.fixture(scope="module", params=[("orbit", None), ("flyover", 15.0)], ids=["orbit", "flyover"])
def house(request, tmp_path_factory):
    """One 640x480 frame of the bundled sample house (``mst synth``): the orbit at 12 m (the house
    fills ~40 % of the frame, on a mottled concrete floor before brick walls) and the flyover 15 m
    above the roof (22 m away, ~130 px wide, on grass/gravel terrain)."""
    import cv2

    from mst.core.camera import read_camera
    from mst.core.trajectory import read_pose_file
    from mst.eval.bench.slam import SAMPLE_MODEL
    from mst.meshtools.formats import load_tracking_model
    from mst.pipeline.synth import SynthConfig, synthesize

    scenario, distance = request.param
    out = tmp_path_factory.mktemp("house") / scenario
    synthesize(scenario, SAMPLE_MODEL, out, SynthConfig(frames=1, distance=distance, aa_samples=4, texture_size=512,
                                                        depth=False))
    T_mc = inv_T(read_pose_file(out / "cMo" / "000000.txt"))
    cam, m = read_camera(out / "camera.json"), load_tracking_model(out / "model.obj")
    img = cv2.imread(str(sorted((out / "rgb").iterdir())[0]))
    return m, cam, T_mc, img, cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)


@pytest.mark.slow
@pytest.mark.timeout(3600)  # 100 searches of ~0.7 s CPU; minutes of wall on a loaded machine
def test_sample_house_converges_in_95_of_100_trials(house):
    """The issue's bound on the bundled sample house. Budget as above: converged = within 0.5 % of
    the distance (6 cm at 12 m, 11 cm at 22 m) and 0.5 deg; the edge tracker from the TRUE pose
    reaches 0.07 % (orbit) and 0.40 % / 0.24 deg (flyover: the house is 130 px wide, its walls' foot
    has little contrast against the terrain) -- the flyover's margin is the tracker's own accuracy.
    Measured 2026-12-02 (these 100 seeds, load ~5): orbit 96, flyover 99 converged, none wrong, the rest
    refused (0.55 / 0.71 s CPU median per search); with "distinct" at 20 px instead of 1 px the flyover
    accepted one WRONG pose (3.5 % / 1.8 deg off, 1.3 px from five right candidates, scoring 0.35 against
    their 0.39). Before (every Canny edge, 6-D random search, 70 % inlier refusal) 0 of 30, all refused."""
    m, cam, T_mc, _, gray = house
    good, wrong = _trials((m, cam, T_mc, None, gray), 100, seed=1)
    assert good >= 95 and wrong == 0, (good, wrong)


def _without_the_model(m, cam, T_mc, img):
    """The frame with the model's image replaced by the ground beside it (the frame's own texture,
    shifted sideways by the model's width): a frame of the same scene that does not show the model."""
    import cv2

    T = inv_T(T_mc)
    Xc = m.vertices @ T[:3, :3].T + T[:3, 3]
    uv = (Xc @ cam.K.T)[:, :2] / Xc[:, 2:3]
    mask = np.zeros(img.shape[:2], np.uint8)
    for f in m.faces:
        cv2.fillPoly(mask, [np.rint(uv[np.asarray(f)]).astype(np.int32)], 255)
    mask = cv2.dilate(mask, np.ones((7, 7), np.uint8)) > 0
    xs = np.flatnonzero(mask.any(0))
    w = int(xs.max() - xs.min() + 10)
    src = np.roll(img, w if xs.max() + w < img.shape[1] else -w, axis=1)
    out = img.copy()
    out[mask] = src[mask]
    return out


@pytest.mark.slow
def test_sample_house_refuses_the_frame_without_the_house(house):
    """A frame that does not show the model (the house replaced by its textured ground) is refused
    from the true pose itself and from noisy guesses: no pose written (``T_cam_model`` None)."""
    import cv2

    m, cam, T_mc, img, _ = house
    gray = cv2.cvtColor(_without_the_model(m, cam, T_mc, img), cv2.COLOR_BGR2GRAY)
    rng = np.random.default_rng(5)
    for i in range(4):
        G = T_mc if i == 0 else _guess(T_mc, rng)
        r = auto_init(gray, m, cam, inv_T(G), AutoInitConfig(seed=i))
        assert not r.ok and r.T_cam_model is None, (i, r.score, r.null_score, r.reason)


def test_a_candidate_a_few_pixels_away_is_a_distinct_pose(view):
    """Refined candidates of one pose agree to ~0.1 px; one whose projection lies 3 px from the best's
    is another answer (distinct for the score margin) while still in the best's basin (agreeing within
    dt_max_px): the rule that refuses the flyover's 3.5 %-off pose, 1.3 px from the right ones."""
    from mst.pipeline.autoinit import _EdgeScorer, _second_best
    from mst.pipeline.tracking.config import TrackConfig

    m, cam, T_mc, _, gray = view
    cfg = AutoInitConfig()
    sc_ = _EdgeScorer(gray, m, cam, inv_T(T_mc), cfg, TrackConfig())
    T_cm = inv_T(T_mc)

    def turned(px):  # the camera turned about its y axis: the image moves ~px sideways
        R = so3_exp(np.array([0.0, px / cam.K[0, 0], 0.0]))
        T = T_cm.copy()
        T[:3, :3], T[:3, 3] = R @ T[:3, :3], R @ T[:3, 3]
        return T

    near, far = turned(0.05), turned(3.0)
    second, agree = _second_best(sc_, [(0.30, T_cm, None), (0.31, near, None)], T_cm, cfg.distinct_px, cfg.dt_max_px)
    assert second is None and agree == 2
    second, agree = _second_best(sc_, [(0.30, T_cm, None), (0.31, far, None)], T_cm, cfg.distinct_px, cfg.dt_max_px)
    assert second == 0.31 and agree == 2
