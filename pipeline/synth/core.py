"""The pure synth core: model triangles + scenario + config -> a :class:`SynthPlan` (camera, poses,
clicks, renderer), then one :class:`SynthFrame` at a time (colour, depth, pixel counts). No files."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from mst.core.camera import Camera
from mst.core.poses import inv_T, make_T, transform_points
from mst.pipeline.synth.config import SynthConfig
from mst.pipeline.synth.scenarios import Scene
from mst.pipeline.synth.scene import build_scene, choose_clicks, kinect_depth


@dataclass
class SynthPlan:
    """Everything a sequence needs before its first frame is rendered."""

    cam: Camera
    R_cm: np.ndarray             #: canonical <- model rotation
    scene: Scene                 #: the resolved scenario (its ``params`` go to scene.json)
    renderer: object             #: :class:`mst.pipeline.render.ShadedRenderer` of the whole scene
    mesh: tuple                  #: (V_all, F_all, material per face): model + environment
    T_model_cam: np.ndarray      #: (N, 4, 4) ground-truth camera poses
    T_cam_model: np.ndarray      #: (N, 4, 4) their inverses (ViSP's cMo)
    click_X: np.ndarray          #: (n, 3) clicked model corners
    click_uv: np.ndarray         #: (n, 2) their frame-0 pixels (with the click noise)
    n_model_tri: int

    def T_model_cam_at(self, s: float) -> np.ndarray:
        """Camera pose at base-trajectory time ``s`` (seconds; sub-frame times for motion blur)."""
        return make_T(self.R_cm.T, np.zeros(3)) @ self.scene.pose(s)


@dataclass
class SynthFrame:
    """One rendered frame."""

    index: int
    bgr: np.ndarray              #: (H, W, 3) uint8
    depth: np.ndarray | None     #: (H, W) float32 metres (0: none); None without depth
    model_px: int                #: pixels showing the model
    edge_px: int                 #: supersampled silhouette/crease pixels


@dataclass
class SynthResult:
    """The summary of a rendered sequence (``--json``)."""

    out_dir: str
    scenario: str
    base: str
    frames: int
    drop: int
    fps: float
    width: int
    height: int
    focal_px: float
    depth: bool
    distance_m: float
    speed_m_s: float
    clicks: int
    frames_without_model: int
    triangles: dict
    setup_s: float
    render_ms_per_frame: float
    total_s: float

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def plan_sequence(scenario: str, cfg: SynthConfig, V: np.ndarray, F: np.ndarray) -> SynthPlan:
    """Camera, scene, renderer, ground-truth poses and frame-0 clicks of a static-scene scenario."""
    cam, R_cm, scene, renderer, mesh = build_scene(scenario, cfg, V, F)
    p = scene.params
    frames, drop, fps = p["frames"], p["drop"], float(cfg.fps)
    T_model_canon = make_T(R_cm.T, np.zeros(3))
    T_model_cam = np.array([T_model_canon @ scene.pose(k * drop / fps) for k in range(frames)])
    T_cam_model = inv_T(T_model_cam)
    click_idx = choose_clicks(renderer, cam, T_cam_model[0], V, F, cfg.n_clicks)
    X_clk = V[click_idx]
    uv_clk = cam.project(transform_points(T_cam_model[0], X_clk))
    if cfg.click_noise > 0:
        uv_clk = uv_clk + np.random.default_rng([int(cfg.seed), 3]).normal(0, cfg.click_noise, uv_clk.shape)
    return SynthPlan(cam, R_cm, scene, renderer, mesh, T_model_cam, T_cam_model, X_clk, uv_clk, len(F))


def render_frame(plan: SynthPlan, cfg: SynthConfig, k: int) -> SynthFrame:
    """Frame ``k``: shaded render (motion blur: sub-frames over the exposure ending at the frame
    time), 8-bit colour with sensor noise, depth (Kinect-like noise with ``depth_noise="kinect"``)."""
    from mst.pipeline import render_kernels as rk

    cam, renderer = plan.cam, plan.renderer
    p = plan.scene.params
    drop, fps = p["drop"], float(cfg.fps)
    s_k = k * drop / fps
    out = renderer.render(cam, plan.T_cam_model[k], aa_samples=cfg.aa_samples,
                          with_cos=cfg.depth and cfg.depth_noise == "kinect")
    rgb = out["rgb"]
    if cfg.motion_blur > 1:
        # average sub-frames over the exposure ending at the frame time (the GT pose)
        acc = rgb.astype(np.float64)
        for j in range(1, cfg.motion_blur):
            s_j = s_k - cfg.shutter * (j / (cfg.motion_blur - 1)) * drop / fps
            acc += renderer.render(cam, inv_T(plan.T_model_cam_at(s_j)), aa_samples=cfg.aa_samples)["rgb"]
        rgb = (acc / cfg.motion_blur).astype(np.float32)
    noise = (np.random.default_rng([int(cfg.seed), k, 1]).integers(0, 2**32, rgb.shape, dtype=np.uint32)
             if cfg.rgb_noise > 0 else np.zeros((0, 0, 0), np.uint32))  # bits of N(0, 1) draws
    bgr = np.empty((cam.height, cam.width, 3), np.uint8)
    rk.encode_bgr8(np.ascontiguousarray(rgb, np.float32), noise, np.float32(cfg.rgb_noise), bgr)
    depth = out["depth"]
    if cfg.depth and cfg.depth_noise == "kinect":
        depth = kinect_depth(depth, out["cos_incidence"], 0.5 * (cam.fx + cam.fy),
                             np.random.default_rng([int(cfg.seed), k, 2]))
    ids = out["ids"]
    model_px = int(np.count_nonzero((ids >= 0) & (ids < plan.n_model_tri)))
    return SynthFrame(k, bgr, depth if cfg.depth else None, model_px, out["n_edge_px"])
