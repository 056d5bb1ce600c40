"""The aids the tracking loop gets: :class:`StandbyAid` (the default: the mono aid switched on only
when the edge poses weaken) and :func:`make_aid`."""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mst.core.camera import Camera
from mst.core.klt import to_gray
from mst.pipeline.depth_io import DepthConfig
from mst.pipeline.slam.aid import ModelAidedSlam
from mst.pipeline.slam.config import SlamConfig
from mst.pipeline.slam.state import STATUS_MODEL


class StandbyAid:
    """The default aid (``--slam auto`` without depth): the mono SLAM switched on only when needed.

    Measured on the real ``teabox.mp4`` (README, tracking section): with the model in view, the
    always-on mono aid does not make the edge poses better (forward-backward error 0.32 px, edges
    only 0.32 px, edges + KLT with the KLT information cap 0.22 px) and costs 2-3x the time. So while the edge poses are
    healthy and strong (``trace(W)`` at least ``wake_info_ratio`` x its running mean) this aid only
    keeps the last ``buffer_frames`` frames with their model poses (references, no work). On the
    first weak or unhealthy edge pose (the model leaving the view, occluded, fast motion) it
    **wakes**: a :class:`ModelAidedSlam` ('mono') is built by replaying the buffered frames with
    their model poses (tracks, triangulated landmarks, keyframes), and from then on it predicts and
    bridges exactly as ``--slam mono``. After ``sleep_after`` strong model frames in a row it goes
    back to standby (its map points are kept for :meth:`landmarks`). The three numbers are
    ``config.standby`` (:class:`~mst.pipeline.slam.config.StandbyConfig`).

    ``standby`` is True while asleep; the tracking loop calls :meth:`needs_wake` after the edge
    pass and :meth:`wake` (which returns the SLAM prediction of the current frame) before
    :meth:`update`. Poses ``T_cam_model`` (4x4); ``W`` the 6x6 edge information (twist order v, w).
    """

    def __init__(self, camera: Camera, config: SlamConfig | Mapping | None = None):
        self.camera, self.config = camera, SlamConfig.from_dict(config)
        sb = self.config.standby
        self.buf: deque[tuple] = deque(maxlen=max(2, sb.buffer_frames))
        self.wake_info_ratio, self.sleep_after = sb.wake_info_ratio, sb.sleep_after_frames
        self.aid: ModelAidedSlam | None = None
        self.info_ref: float | None = None
        self.n_strong = 0
        self._retired: list[np.ndarray] = []
        self._fired: list[int] = []
        self._refuted: list[int] = []
        self._budget: list[int] = []
        self._drift_log: dict[int, tuple[float, float]] = {}
        self._reloc = {"taken": 0, "gated": 0}
        self.stats = {"wakes": 0, "sleeps": 0, "frames_active": 0, "wake_frames": []}
        self.timing_ms = {"wake": 0.0}

    @property
    def standby(self) -> bool:
        """True while asleep (no mono map)."""
        return self.aid is None

    @property
    def static_world_fired(self) -> list[int]:
        """Frames where the static-world check of the (current or an earlier) mono map fired."""
        return self._fired + (self.aid.static_world_fired if self.aid is not None else [])

    @property
    def map_refuted(self) -> list[int]:
        """Frames whose map pose the image refuted (:meth:`ModelAidedSlam.refute_map_pose`)."""
        return self._refuted + (self.aid.map_refuted if self.aid is not None else [])

    @property
    def drift_budget_frames(self) -> list[int]:
        """Frames whose map pose was beyond the drift budget (:meth:`ModelAidedSlam.within_budget`)."""
        return self._budget + (self.aid.drift_budget_frames if self.aid is not None else [])

    @property
    def drift_log(self) -> dict[int, tuple[float, float]]:
        """Frame -> (bound / distance, bound deg) of every map pose (:mod:`mst.pipeline.slam.drift`)."""
        return {**self._drift_log, **(self.aid.drift_log if self.aid is not None else {})}

    @property
    def map_relocalisations(self) -> dict[str, int]:
        """The maps' relocalisations: ``taken`` and ``gated`` (refused by the motion gate,
        :meth:`ModelAidedSlam.reloc_gate_m`), over every active stretch."""
        cur = self.aid.map_relocalisations if self.aid is not None else {}
        return {k: v + cur.get(k, 0) for k, v in self._reloc.items()}

    def within_budget(self, k: int, distance_m: float) -> bool:
        """The active map's pose of frame ``k`` is within its drift budget (True when asleep)."""
        return self.aid.within_budget(k, distance_m) if self.aid is not None else True

    def refute_map_pose(self, k: int) -> bool:
        """The image refutes the active map's pose of frame ``k``: see :meth:`ModelAidedSlam.refute_map_pose`."""
        return self.aid.refute_map_pose(k) if self.aid is not None else False

    def _strong(self, W: np.ndarray | None) -> bool:
        if W is None or not np.isfinite(W).all():
            return False
        return self.info_ref is None or float(np.trace(W)) >= self.wake_info_ratio * self.info_ref

    def needs_wake(self, healthy: bool, W: np.ndarray | None) -> bool:
        """True when asleep and this frame's edge pose is unhealthy or weak."""
        return self.aid is None and not (healthy and self._strong(W))

    def wake(self, k: int, gray: np.ndarray, T_cam_model_prev: np.ndarray | None) -> np.ndarray | None:
        """Build the mono SLAM from the buffered frames; return its prediction for frame ``k``."""
        import time

        t0 = time.perf_counter()
        self.aid = ModelAidedSlam("mono", self.camera, self.config)
        for kb, gb, Tb, Wb, Cb in self.buf:
            self.aid.predict(kb, gb, Tb)
            self.aid.update(kb, gb, Tb, Wb, True, cov_edges=Cb)
        self.buf.clear()
        self.n_strong = 0
        self.stats["wakes"] += 1
        self.stats["wake_frames"].append(int(k))
        T = self.aid.predict(k, gray, T_cam_model_prev)
        self.timing_ms["wake"] += (time.perf_counter() - t0) * 1e3
        return T

    def predict(self, k: int, gray: np.ndarray, T_cam_model_prev: np.ndarray | None) -> np.ndarray | None:
        """Asleep: None (the tracker starts from its previous pose); awake: the mono prediction."""
        return None if self.aid is None else self.aid.predict(k, gray, T_cam_model_prev)

    def update(self, k: int, gray: np.ndarray, T_cam_model_edges: np.ndarray | None,
               W: np.ndarray | None, healthy: bool, weak_edge_pose: np.ndarray | None = None,
               cov_edges: np.ndarray | None = None, distance_fn=None) -> tuple[np.ndarray | None, str]:
        """As :meth:`ModelAidedSlam.update`; asleep, a healthy strong edge pose is output as is."""
        if self.aid is None and not self.needs_wake(healthy, W):
            self.buf.append((k, to_gray(gray), np.asarray(T_cam_model_edges, float).copy(), np.asarray(W, float),
                             None if cov_edges is None else np.asarray(cov_edges, float).copy()))
            tr = float(np.trace(W))
            self.info_ref = tr if self.info_ref is None else 0.9 * self.info_ref + 0.1 * tr
            return np.asarray(T_cam_model_edges, float).copy(), STATUS_MODEL
        if self.aid is None:  # the loop did not call wake() (hook contract): wake now
            self.wake(k, gray, T_cam_model_edges)
        T_out, status = self.aid.update(k, gray, T_cam_model_edges, W, healthy, weak_edge_pose, cov_edges, distance_fn)
        self.stats["frames_active"] += 1
        self.n_strong = self.n_strong + 1 if (status == STATUS_MODEL and healthy and self._strong(W)) else 0
        if self.n_strong >= self.sleep_after:
            self._retire()
            self.stats["sleeps"] += 1
        return T_out, status

    def landmarks(self) -> np.ndarray:
        """(N, 3) model-frame map points of every active stretch (empty when it never woke)."""
        parts = self._retired + ([self.aid.landmarks()] if self.aid is not None else [])
        parts = [p for p in parts if len(p)]
        return np.concatenate(parts, 0) if parts else np.zeros((0, 3))

    def close(self) -> None:
        """Retire the active map (its points stay in :meth:`landmarks`) and drop the buffer."""
        if self.aid is not None:
            self._retire()
        self.buf.clear()

    def _retire(self) -> None:
        """Keep what the active map found (points, fired checks, refuted and over-budget frames, the
        drift log, relocalisation counts), close it and go back to standby."""
        a = self.aid
        self._retired.append(a.landmarks())
        self._fired += a.static_world_fired
        self._refuted += a.map_refuted
        self._budget += a.drift_budget_frames
        self._drift_log.update(a.drift_log)
        for k, v in a.map_relocalisations.items():
            self._reloc[k] += v
        a.close()
        self.aid = None


def make_aid(mode: str, camera: Camera, config: SlamConfig | Mapping | None = None, depth_dir: Path | None = None,
             depth_camera: Camera | None = None, T_depth_color: np.ndarray | None = None,
             depth: DepthConfig | None = None) -> ModelAidedSlam | StandbyAid:
    """Create the SLAM aid for the tracking loop.

    ``mode``: ``'mono'`` (landmarks triangulated with the known poses), ``'rgbd'`` (landmarks lifted
    from the depth frames in ``depth_dir``, the k-th sorted file for frame k) or ``'standby'``
    (:class:`StandbyAid`: mono, switched on when needed). ``config``: the ``slam`` section, a
    :class:`SlamConfig` or its mapping (strict: an unknown key is a ConfigError naming it).
    ``depth``: how depth frames are read and trusted (the track's shared ``depth`` section:
    ``scale`` raw units per metre, ``min_m``/``max_m``, ``edge_rel``); None:
    :func:`~mst.pipeline.slam.config.slam_depth_config`. ``depth_camera``: the depth camera's
    intrinsics when the depth is not registered to colour; ``T_depth_color`` (4x4) maps
    colour-camera points to the depth camera (identity when None).
    """
    if mode == "standby":
        return StandbyAid(camera, config)
    return ModelAidedSlam(mode, camera, config, depth_dir, depth_camera, T_depth_color, depth)
