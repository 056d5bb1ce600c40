"""Model-aided SLAM aid (mst.pipeline.slam) on rendered textured scenes with ground truth.

The aid is driven the way the tracking loop drives it (``predict`` then ``update`` per frame), with
"edge poses" derived from the ground truth: GT + Gaussian noise drawn from ``W^-1`` (W from a
synthetic Jacobian of the model's corners), withheld (``None``, unhealthy) while the model is out of
view. This proves the fusion logic independently of the edge tracker; the end-to-end runs with
``mst track`` are in ``test_slam_track.py``.

Scenes: Open3D ray casting of a 1 m cube (the "model") inside a 12 m x 12 m x 5 m room, every
surface with a smooth procedural texture (so KLT has corners); 320x240 pixels, f = 250 px.
"""

from __future__ import annotations

import numpy as np
import pytest

from mst.core.camera import Camera
from mst.core.poses import inv_T, make_T, pose_error, se3_exp
from mst.core.poses import look_at as poses_look_at
from mst.pipeline import slam

W_PX, H_PX = 320, 240
CAM = Camera(250.0, 250.0, 159.5, 119.5, W_PX, H_PX)
CUBE = np.array([[x, y, z] for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (0.0, 1.0)])


# ---------------------------------------------------------------------------- scene + trajectories
class TexturedScene:
    """A textured cube in a textured room, rendered by ray casting (image + z-depth in metres)."""

    def __init__(self, seed: int = 0):
        import open3d as o3d

        def box(lo, hi, inward=False):
            m = o3d.geometry.TriangleMesh.create_box(*(np.subtract(hi, lo)))
            m.translate(lo)
            if inward:
                m.triangles = o3d.utility.Vector3iVector(np.asarray(m.triangles)[:, ::-1])
            return o3d.t.geometry.TriangleMesh.from_legacy(m)

        self.o3d = o3d
        self.rs = o3d.t.geometry.RaycastingScene()
        self.rs.add_triangles(box([-0.5, -0.5, 0.0], [0.5, 0.5, 1.0]))
        self.rs.add_triangles(box([-6, -6, -1.0], [6, 6, 4.0], inward=True))
        rng = np.random.default_rng(seed)
        d = rng.normal(size=(12, 3))
        self.freq = d / np.linalg.norm(d, axis=1, keepdims=True) * rng.uniform(4, 20, (12, 1))
        self.phase = rng.uniform(0, 2 * np.pi, 12)

    def render(self, T_cam_world: np.ndarray, cam: Camera = CAM) -> tuple[np.ndarray, np.ndarray]:
        o3d = self.o3d
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            intrinsic_matrix=o3d.core.Tensor(cam.K), extrinsic_matrix=o3d.core.Tensor(T_cam_world),
            width_px=cam.width, height_px=cam.height)
        t = self.rs.cast_rays(rays)["t_hit"].numpy()
        r = rays.numpy()
        X = (r[..., :3] + r[..., 3:] * t[..., None]).reshape(-1, 3)
        tex = np.tanh(0.6 * np.sin(X @ self.freq.T + self.phase).sum(1)) * 100 + 128
        img = np.clip(tex, 0, 255).astype(np.uint8).reshape(cam.height, cam.width)
        depth = np.where(np.isfinite(t), t, 0).astype(np.float32)   # rays have z = 1: t is z-depth
        return img, depth


def look_at(C, target=(0.0, 0.0, 0.5), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """T_cam_world of a camera at C looking at target."""
    return inv_T(poses_look_at(C, target, up))


def orbit(n: int, step_deg: float = 1.0, radius: float = 3.0) -> np.ndarray:
    a = np.radians(np.arange(n) * step_deg)
    return np.array([look_at([radius * np.cos(t), radius * np.sin(t), 1.2]) for t in a])


def corridor(n: int, away_deg: float = 70.0) -> np.ndarray:
    """Slow orbit while the view pans away from the cube (out of view mid-sequence) and back."""
    out = []
    for i in range(n):
        a = np.radians(i * 0.5)
        f = i / (n - 1)
        yaw = np.radians(away_deg * np.clip(min((f - 0.15) / 0.15, (0.85 - f) / 0.15), 0, 1))
        Ry = np.array([[np.cos(yaw), 0, np.sin(yaw)], [0, 1, 0], [-np.sin(yaw), 0, np.cos(yaw)]])
        out.append(make_T(Ry, np.zeros(3)) @ look_at([3 * np.cos(a), 3 * np.sin(a), 1.2]))
    return np.array(out)


def cube_visible(T: np.ndarray, cam: Camera = CAM) -> bool:
    Xc = CUBE @ T[:3, :3].T + T[:3, 3]
    uv = Xc[:, :2] / Xc[:, 2:] * [cam.fx, cam.fy] + [cam.cx, cam.cy]
    inside = (Xc[:, 2] > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
    return inside.sum() >= 6


@pytest.fixture(scope="module")
def scene():
    return TexturedScene()


def render_sequence(scene, Ts, tmp_path, with_depth=True):
    imgs = []
    if with_depth:
        (tmp_path / "depth").mkdir(exist_ok=True)
    for i, T in enumerate(Ts):
        img, d = scene.render(T)
        imgs.append(img)
        if with_depth:
            np.save(tmp_path / "depth" / f"{i:06d}.npy", d)
    return imgs


def edge_pose(T_true, rng, gain=50.0):
    """A synthetic edge-tracker result: W from the cube corners' Jacobian, pose = GT + N(0, W^-1)."""
    W = slam.pose_information(CAM.K, CUBE @ T_true[:3, :3].T + T_true[:3, 3]) * gain
    # Cholesky, not numpy's default SVD: the SVD's singular-vector signs and last bits depend on the
    # LAPACK kernel (OPENBLAS_CORETYPE), which changed the drawn noise in its 3rd digit between CPUs
    delta = rng.multivariate_normal(np.zeros(6), np.linalg.inv(W), method="cholesky")
    return se3_exp(delta) @ T_true, W


def drive(aid, Ts, imgs, rng, visible=None, tamper=None):
    """Run the aid like the tracking loop; returns statuses and per-frame (position err, angle err)."""
    statuses, errs = [], []
    T_prev = Ts[0]
    for k, (T, img) in enumerate(zip(Ts, imgs)):
        aid.predict(k, img, T_prev)
        vis = cube_visible(T) if visible is None else visible[k]
        if vis:
            Te, W = edge_pose(T, rng)
            if tamper is not None and k in tamper:
                Te = tamper[k] @ Te
            T_out, st = aid.update(k, img, Te, W, True)
        else:
            T_out, st = aid.update(k, img, None, None, False)
        statuses.append(st)
        if T_out is None:
            errs.append((np.nan, np.nan))
        else:
            T_prev = T_out
            dt, dr = pose_error(inv_T(T_out), inv_T(T))
            errs.append((float(dt), float(dr)))
    return np.array(statuses), np.array(errs)


# ---------------------------------------------------------------------------- unit tests
def test_depth_lift_honours_depth_camera_and_extrinsic(scene, tmp_path):
    """A depth frame in a separate depth camera (other intrinsics, 5 cm baseline) lifts colour
    pixels to the same model points as a registered depth frame."""
    T = look_at([3.0, 0.4, 1.3])
    img, depth_reg = scene.render(T)
    dcam = Camera(200.0, 200.0, 150.0, 110.0, 300, 220)
    T_depth_color = make_T(np.eye(3), [-0.05, 0.0, 0.0])        # colour -> depth
    _, depth_d = scene.render(T_depth_color @ T, dcam)
    a_reg = slam.ModelAidedSlam("rgbd", CAM, {}, _write_depth(tmp_path / "reg", depth_reg), None, None)
    a_ext = slam.ModelAidedSlam("rgbd", CAM, {}, _write_depth(tmp_path / "ext", depth_d), dcam, T_depth_color)
    import cv2

    uv = cv2.goodFeaturesToTrack(img, 200, 0.01, 8).reshape(-1, 2)
    X_reg = a_reg._depth_at(depth_reg, uv)
    X_ext = a_ext._depth_at(depth_d, uv)
    ok = np.isfinite(X_reg[:, 0]) & np.isfinite(X_ext[:, 0])
    assert ok.sum() > 100
    # the registered lift is exact up to pixel rounding; the unregistered one up to depth-pixel rounding
    dz = np.abs(X_reg[ok, 2] - X_ext[ok, 2]) / X_reg[ok, 2]
    assert np.median(dz) < 0.005 and np.percentile(dz, 90) < 0.02
    # and the registered lift matches the ray-cast surface: project back to the same pixels
    uvp = X_reg[ok, :2] / X_reg[ok, 2:] * [CAM.fx, CAM.fy] + [CAM.cx, CAM.cy]
    assert np.abs(uvp - uv[ok]).max() < 1e-6


def _write_depth(folder, depth):
    folder.mkdir()
    np.save(folder / "000000.npy", depth)
    return folder


def test_local_ba_guard_accepts_good_priors_and_rejects_a_wrong_one():
    """Guarded constrained BA: correct priors pull perturbed keyframes back; a grossly wrong,
    over-confident prior is down-weighted or dropped instead of dragging the map."""
    rng = np.random.default_rng(0)
    Ts = orbit(60)[::10]
    X = rng.uniform([-2, -2, -0.5], [2, 2, 1.5], (300, 3))

    def make(prior_of):
        aid = slam.ModelAidedSlam("mono", CAM, {})
        aid.lm = {i: x.copy() for i, x in enumerate(X)}
        for j, T in enumerate(Ts):
            uv, z = aid._project(T, X)
            ok = (z > 0) & (uv[:, 0] > 0) & (uv[:, 0] < W_PX) & (uv[:, 1] > 0) & (uv[:, 1] < H_PX)
            uv = uv[ok] + rng.normal(0, 0.3, (ok.sum(), 2))
            W = slam.pose_information(CAM.K, X[ok] @ T[:3, :3].T + T[:3, 3]) / 0.3**2
            aid.kfs.append(slam.Keyframe(j, T.copy(), np.flatnonzero(ok), uv.astype(np.float32), prior_of(j, T), W))
        return aid

    # 1) correct priors; keyframes 2.. perturbed by ~1 cm / 0.5 deg
    aid = make(lambda j, T: T.copy())
    for kf in list(aid.kfs)[2:]:
        kf.T_cam_model = se3_exp(np.r_[rng.normal(0, 0.01, 3), rng.normal(0, 0.01, 3)]) @ kf.T_cam_model
    aid._local_ba("model")
    err = [pose_error(inv_T(kf.T_cam_model), inv_T(T))[0] for kf, T in zip(aid.kfs, Ts)]
    assert aid.stats["ba_prior_accepted"] == 1
    assert max(err) < 0.003
    # 2) one keyframe's prior is 10 cm off but claims sub-mm precision
    bad = make(lambda j, T: (make_T(np.eye(3), [0.1, 0, 0]) @ T) if j == 4 else T.copy())
    bad._local_ba("model")
    assert bad.stats["ba_prior_accepted"] == 0
    assert bad.stats["ba_prior_downweighted"] + bad.stats["ba_prior_dropped"] == 1
    err = [pose_error(inv_T(kf.T_cam_model), inv_T(T))[0] for kf, T in zip(bad.kfs, Ts)]
    assert max(err) < 0.03


# ---------------------------------------------------------------------------- sequences
# mono: slow (suite time); the mono hidden stretch is in the default suite through test_slam_track / test_slam_drift
@pytest.mark.parametrize("mode", ["rgbd", pytest.param("mono", marks=pytest.mark.slow)])
def test_corridor_model_out_of_view_no_loss(scene, tmp_path, mode):
    """The cube leaves the view for 40+ frames: never lost, SLAM carries the pose, the model pose
    takes over again on return."""
    Ts = corridor(120)
    imgs = render_sequence(scene, Ts, tmp_path, with_depth=mode == "rgbd")
    vis = np.array([cube_visible(T) for T in Ts])
    out = np.flatnonzero(~vis)
    assert len(out) >= 40 and out[-1] - out[0] + 1 == len(out)  # one contiguous out-of-view stretch
    aid = slam.make_aid(mode, CAM, {}, tmp_path / "depth" if mode == "rgbd" else None, None, None)
    st, err = drive(aid, Ts, imgs, np.random.default_rng(1))
    assert not (st == "lost").any()
    assert (st[~vis] == "slam").all()
    assert (st[vis] == "model").mean() > 0.95
    # Drift while out of view, against the aid's own drift model: its filter grows the pose
    # covariance by a random walk of drift_rel x depth (position) and drift_deg (rotation) per frame,
    # and at the model's return the chi-square gate compares the edge pose with that covariance. A
    # drift beyond 3 sigma of the walk after the stretch would make the gate reject the correct edge
    # pose, so 3 sigma is the property (the max of a random walk exceeds it with probability < 0.3 %
    # per axis). The drift itself is a random variable: over seeds and BLAS kernels it spans about
    # 1.2-1.7 % (rgbd) and 3.5-4.5 % (mono) of the 3 m distance; the old bounds (1.5 %, 6 %) had
    # been fitted to one run and failed on another CPU.
    dist = 3.0
    rate = aid.cfg.drift_rel_per_frame or (0.001 if mode == "rgbd" else 0.005)
    deg = aid.cfg.drift_deg_per_frame or (0.05 if mode == "rgbd" else 0.2)
    walk = np.sqrt(len(out))
    assert np.nanmax(err[~vis, 0]) < 3 * rate * dist * walk
    assert np.nanmax(err[~vis, 1]) < 3 * deg * walk
    assert len(aid.kfs) <= aid.cfg.ba_window
    aid.close()


def test_gate_rejects_a_wrong_edge_pose(scene, tmp_path):
    """A 'healthy' edge pose that is 10 cm off (a wrong match) must not drag the SLAM. It differs from
    the map by 3 % of the distance, more than the output bound (1 %): neither pose is output on
    those frames (the map cannot tell a wrong match from a moving object yet); the map is kept
    and carries on correctly afterwards. The same offset three times is no motion: the
    static-world check stays quiet."""
    Ts = orbit(40)
    imgs = render_sequence(scene, Ts, tmp_path)
    aid = slam.make_aid("rgbd", CAM, {}, tmp_path / "depth", None, None)
    wrong = {k: make_T(np.eye(3), [0.1, 0.0, 0.0]) for k in (25, 26, 27)}
    st, err = drive(aid, Ts, imgs, np.random.default_rng(2), tamper=wrong)
    assert list(st[[25, 26, 27]]) == ["lost"] * 3
    assert (st[28:] == "model").all() and err[28:, 0].max() < 0.02
    assert aid.stats["gate_rejects"] == 3 and aid.stats["contradictions"] == 3
    assert aid.static_world_fired == []


def test_relocalisation_after_blackout(scene, tmp_path):
    """Frames with no image content (lens covered) lose everything; the aid relocalises against
    its keyframes when the view comes back, with no edge pose."""
    Ts = orbit(50, step_deg=0.5)
    imgs = render_sequence(scene, Ts, tmp_path)
    for k in range(30, 34):
        imgs[k] = np.zeros_like(imgs[k])
    vis = np.array([k < 30 for k in range(len(Ts))])   # no edge pose after the blackout
    aid = slam.make_aid("rgbd", CAM, {}, tmp_path / "depth", None, None)
    st, err = drive(aid, Ts, imgs, np.random.default_rng(3), visible=vis)
    assert (st[30:34] == "lost").all()
    assert aid.stats["relocalisations"] >= 1
    assert (st[34:] == "slam").all()
    assert np.nanmax(err[34:, 0]) < 0.05


def test_map_relocalisation_may_not_teleport_the_camera(scene, tmp_path):
    """A relocalisation of the map is gated by the camera's motion: after 30 frames of an orbit (1 deg,
    5.2 cm a frame at 3 m), the image of frame 0 (1.50 m back along the orbit) matches the keyframes and
    PnP finds its pose, yet one frame after the last map pose the camera cannot be there (the gate:
    0.1 x the scene depth, 7.5 m to the room's walls, + 3 x 5.4 cm, the camera's steps = 0.9 m): refused and counted.
    Without the frame index (no gate) the same image relocalises onto frame 0's pose; the image of
    where the camera is (frame 29) is taken through the gate; and the gate opens with the frames since
    the last map pose (at frame 40 it is 2.5 m), as a long loss allows a long way."""
    Ts = orbit(31)
    imgs = render_sequence(scene, Ts, tmp_path)
    aid = slam.make_aid("rgbd", CAM, {}, tmp_path / "depth", None, None)
    drive(aid, Ts[:30], imgs[:30], np.random.default_rng(3))
    c = lambda T: -T[:3, :3].T @ T[:3, 3]  # noqa: E731
    jump = float(np.linalg.norm(c(Ts[0]) - c(Ts[29])))
    assert 1.4 < jump < 1.7 and aid.reloc_gate_m(30) < jump < aid.reloc_gate_m(40)
    assert aid._relocalise(imgs[0], 30) is None and aid.stats["reloc_gated"] >= 1
    # PnP against landmarks lifted under the noisy edge poses: about 0.1 m off; what matters is which
    # pose it finds (frame 0's, 1.5 m from the camera's), so a fifth of the jump
    T = aid._relocalise(imgs[0])
    assert T is not None and np.linalg.norm(c(T) - c(Ts[0])) < 0.2 * jump
    T = aid._relocalise(imgs[29], 30)
    assert T is not None and np.linalg.norm(c(T) - c(Ts[29])) < 0.2 * jump
    assert aid.reloc_gate_m(40) > jump
    assert aid.map_relocalisations["taken"] == 2 and aid.map_relocalisations["gated"] >= 1
    aid.close()


def test_relocalisation_gate_remembers_the_cruise_speed_through_a_hover():
    """The gate grows with the camera's speed, the 75th percentile of its steps between output poses:
    after 30 frames at 0.2 m a frame and 10 hovering, 50 frames after the last pose the gate is
    0.1 x scene depth + 3 x 0.2 m x 50 (a UAV that hovered, turned, was lost and flew on is looked for
    where it can have flown); one pose 5 m off among them (a sliver's edge pose) does not open it."""
    aid = slam.make_aid("mono", CAM, {}, None, None, None)
    aid.scene_depth = 80.0
    x = list(np.arange(30) * 0.2) + [5.8] * 10
    x[20] += 5.0  # one pose off by 5 m
    for k, xk in enumerate(x):
        aid._note_output(k, np.array([xk, 0.0, 40.0]))
    assert aid.reloc_gate_m(39) == pytest.approx(8.0)
    assert aid.reloc_gate_m(89) == pytest.approx(8.0 + 3 * 0.2 * 50)
    aid.close()


@pytest.mark.parametrize("mode", ["rgbd", pytest.param("mono", marks=pytest.mark.slow)])
def test_static_world_check_object_on_a_turntable(scene, tmp_path, mode):
    """The camera orbits slowly; from frame 20 the object turns on a turntable (2 deg/frame) in the
    still room that the map is made of. The edge poses (object frame) keep disagreeing with the map
    by a growing offset: the static-world check must fire within its window, the output must then
    follow the object (model poses), and no map pose may be output as a pose in model coordinates
    while the object moves; when the turntable stops, the map bridges again."""
    n, start, stop = 60, 20, 40
    Ts_world = orbit(n, step_deg=0.5)
    imgs = render_sequence(scene, Ts_world, tmp_path, with_depth=mode == "rgbd")
    turn = np.radians(2.0 * np.clip(np.arange(n) - start, 0, stop - start))
    T_world_obj = [make_T(np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]), np.zeros(3))
                   for a in turn]
    Ts = [Tw @ To for Tw, To in zip(Ts_world, T_world_obj)]  # T_cam_obj: what the edges measure
    vis = np.ones(n, bool)
    vis[[45, 46]] = False  # after the stop: two frames without an edge pose, the map must bridge them
    aid = slam.make_aid(mode, CAM, {}, tmp_path / "depth" if mode == "rgbd" else None, None, None)
    rng = np.random.default_rng(5)
    st, err = [], []
    T_prev = Ts[0]
    for k in range(n):
        aid.predict(k, imgs[k], T_prev)
        if vis[k]:
            Te, W = edge_pose(Ts[k], rng)
            T_out, s = aid.update(k, imgs[k], Te, W, True)
        else:
            T_out, s = aid.update(k, imgs[k], None, None, False)
        st.append(s)
        err.append(np.nan if T_out is None else float(pose_error(inv_T(T_out), inv_T(Ts[k]))[1]))
        T_prev = T_out if T_out is not None else T_prev
    st, err = np.array(st), np.array(err)
    fired = aid.static_world_fired
    window = aid.cfg.static_world_frames
    # fired within the check's window once the motion exceeds the gate (a few frames at 2 deg/frame)
    assert fired and start < fired[0] <= start + 3 + window
    # every pose output as a model-frame pose is right (the bound 2 deg; the edge noise ~0.1)
    assert np.nanmax(err[st != "lost"]) < 2.0
    # while the object moves no map pose is output
    assert not (st[fired[0]:stop] == "slam").any()
    # after the stop the map agrees again and bridges the frames without edges
    assert not aid.moving_hold and (st[[45, 46]] == "slam").all()
    aid.close()


def test_rgbd_reads_depth_with_the_depth_scale(scene, tmp_path):
    """TUM RGB-D style depth (16-bit PNG, 5000 per metre) read with ``depth.scale = 5000`` gives the
    same poses as the same depth in millimetres (the default scale): the integers differ by x5, the
    metres are the same float32 quotient (:func:`mst.pipeline.depth_io.units_to_metres`), so the two
    runs are the same run. Read with the default scale, the 5000-scaled depth is 5x too far and the
    map is wrong (before #10 ``track`` read 16-bit depth as millimetres only). (Before the quotient,
    the reciprocal's rounding left the last bit of some pixels apart, and one RANSAC decision turned
    that into 1.3 mm on another CPU: a tolerance on the poses was a fit to one machine.)"""
    import cv2

    from mst.pipeline.depth_io import read_depth

    Ts = orbit(20)
    imgs = render_sequence(scene, Ts, tmp_path)
    for name in ("mm", "tum"):
        (tmp_path / name).mkdir()
    for i in range(len(Ts)):
        mm = np.rint(np.load(tmp_path / "depth" / f"{i:06d}.npy") * 1000.0).astype(np.uint16)
        cv2.imwrite(str(tmp_path / "mm" / f"{i:06d}.png"), mm)
        cv2.imwrite(str(tmp_path / "tum" / f"{i:06d}.png"), mm * np.uint16(5))
    for i in (0, len(Ts) - 1):
        d_mm = read_depth(tmp_path / "mm" / f"{i:06d}.png", 1000.0)
        assert np.count_nonzero(d_mm) and np.array_equal(read_depth(tmp_path / "tum" / f"{i:06d}.png", 5000.0), d_mm)
    runs = {}
    for name, scale in (("mm", 1000.0), ("tum", 5000.0), ("tum_as_mm", 1000.0)):
        folder = tmp_path / name.split("_")[0]
        aid = slam.make_aid("rgbd", CAM, {}, folder, None, None, slam.slam_depth_config().replace(scale=scale))
        runs[name] = drive(aid, Ts, imgs, np.random.default_rng(4), visible=np.arange(len(Ts)) < 10)
    (st_mm, e_mm), (st_tum, e_tum), (_, e_bad) = runs["mm"], runs["tum"], runs["tum_as_mm"]
    assert (st_mm[10:] == "slam").all() and list(st_tum) == list(st_mm)
    # the same metres in, the same poses out (one process, the same code path)
    np.testing.assert_array_equal(e_tum, e_mm)
    assert np.nanmax(e_mm[10:, 0]) < 0.02
    assert not (e_bad[10:, 0] < 0.02).all()  # lost (NaN) or wrong: not the bridged poses
