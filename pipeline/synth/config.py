"""The settings of ``mst synth`` (:class:`SynthConfig`) and the scenario names.

Field names are those of ``scene.json`` (format version 1, the layout ``--from-scene`` reads back),
so they keep their historical names; units are stated in each field's help (metres, seconds,
pixels, degrees).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from mst.core.config import Config, param
from mst.errors import ConfigError

SCENARIOS = ("orbit", "corridor", "flyover", "uav", "fpv", "fast", "turntable", "carried", "leave", "occluder", "blackout")
DYNAMIC = ("turntable", "carried", "leave", "occluder", "blackout")  #: moving object / interrupted view: pipeline/synth/dynamic.py
BASE_SCENARIOS = ("orbit", "corridor", "flyover", "uav", "fpv")
DEFAULT_FRAMES = {"orbit": 120, "corridor": 150, "flyover": 120, "uav": 240, "fpv": 150, "fast": 60, "turntable": 80,
                  "carried": 80, "leave": 90, "occluder": 60, "blackout": 60}
UP_AXES = {"z": (0, 0, 1), "-z": (0, 0, -1), "y": (0, 1, 0), "-y": (0, -1, 0), "x": (1, 0, 0), "-x": (-1, 0, 0)}

#: fields added after scene.json format 1 was fixed: written into scene.json only when not at their
#: default, so that sequences rendered without them keep byte-identical scene files
LATER_FIELDS = {"video_codec": "mp4v", "pitch_deg": None}

# material ids (also the ``label`` face property of scene.ply)
MODEL, FLOOR, WALL, CEILING = 0, 1, 2, 3


@dataclass
class SynthConfig(Config):
    """Parameters of :func:`~mst.pipeline.synth.synthesize` (``None`` = scenario default, resolved
    into scene.json). Units: metres, seconds, pixels, degrees."""

    frames: int | None = param(None, min=1, help="output frames (default: orbit 120, corridor 150, flyover 120, fast 60)")
    fps: float = param(30.0, min=0, min_open=True, help="frame rate, frames/s; gt.txt time = frame index / fps")
    width: int = param(640, min=16, help="image width, px")
    height: int = param(480, min=16, help="image height, px")
    focal_px: float | None = param(None, min=0, min_open=True, help="fx = fy, px (default 525 * width / 640)")
    speed: float | None = param(None, min=0, help="camera speed, m/s (default: the scenario's pace)")
    distance: float | None = param(None, min=0, min_open=True,
                                   help="camera-to-model distance (orbit/corridor) or height above it (flyover), m")
    seed: int = param(0, help="seed of textures and noise")
    drop: int | None = param(None, min=1, help="keep every drop-th frame of the base trajectory (fast: 8, else 1)")
    base: str = param("orbit", choices=BASE_SCENARIOS, help="base scenario of 'fast'")
    depth: bool = param(True, help="write depth/ (16-bit PNG mm + float32 .npy m)")
    depth_noise: str = param("none", choices=("none", "kinect"), help="structured-light depth noise, quantisation, holes")
    rgb_noise: float = param(2.0, min=0, help="colour noise sigma, 8-bit levels (near-Gaussian: sum of 4 uniforms)")
    motion_blur: int = param(1, min=1, help="sub-frame renders averaged per frame (1: none)")
    shutter: float = param(0.5, help="exposure as a fraction of the frame interval (motion blur)")
    model_texture: bool = param(False, help="texture the model too (default: flat, per-face shading)")
    floor: str = param("concrete", choices=("concrete", "tiles"), help="orbit/corridor floor texture (flyover: terrain)")
    environment: bool = param(True, help="ground/walls around the model")
    click_noise: float = param(0.0, min=0, help="Gaussian noise added to the clicks' u, v, px")
    n_clicks: int = param(6, min=4, help="clicked corners")
    up: str = param("z", choices=tuple(UP_AXES), help="the model's up axis")
    video: bool = param(False, help="also write video.mp4")
    video_codec: str = param("mp4v", choices=("mp4v", "h264"), help="video.mp4 codec (h264: libx264 through imageio-ffmpeg, crf 23, as a drone records)")
    pitch_deg: float | None = param(None, min=-89, max=89,
                                    help="uav/fpv camera pitch below the horizon, deg (default: uav 45, fpv 8)")
    aa_samples: int = param(16, choices=(0, 4, 8, 16), help="sub-pixel rays per silhouette/crease pixel")
    texture_size: int = param(2048, min=64, help="texels per texture tile side (a power of two)")
    nthreads: int = param(0, min=0, help="ray-casting threads (0: all cores)")

    def check(self) -> None:
        if not math.isfinite(self.fps):
            raise ConfigError("fps", f"must be finite, got {self.fps:g}")
        if self.speed is not None and not math.isfinite(self.speed):
            raise ConfigError("speed", f"must be finite, got {self.speed:g}")
        if self.texture_size & (self.texture_size - 1):
            raise ConfigError("texture_size", f"must be a power of two, got {self.texture_size}")
