"""mst.pipeline.synth: synthetic colour / depth sequences of a model with ground truth (``mst synth``).

Holds the config, scenarios, scene building, the pure core (plan + render one frame), the writers
and the runner :func:`synthesize`; imports :mod:`mst.core`, ``render``/``textures`` and meshtools I/O.

Modules: ``config`` (:class:`SynthConfig`, scenario names), ``scenarios`` (trajectories and rooms),
``scene`` (:func:`build_scene`, model colours, clicks, depth noise), ``core`` (:func:`plan_sequence`,
:func:`render_frame`), ``writers`` (the sequence folder and its files), ``runner``
(:func:`synthesize`, :func:`synthesize_from_scene`), ``dynamic`` (turntable, occluder, blackout).

Frames and units: everything (model, environment, camera poses) is expressed in the *model frame*,
in metres. Scenarios are designed in a *canonical frame* whose +z is the model's up axis
(``config.up``, default ``z``); ``R_model_canon`` maps it back. The camera frame is x right, y down,
z forward; ``T_cam_model`` is ViSP's cMo; TUM files hold ``T_model_cam``.

Output folder (the layout the other stages read)::

    rgb/000000.png ...     8-bit colour (PNG), Lambertian shading, sensor noise
    depth/000000.png       uint16 millimetres, 0 = no depth       (with config.depth)
    depth/000000.npy       float32 metres, 0 = no depth
    video.mp4              the colour frames (mp4v)                 (with config.video)
    camera.json            intrinsics (mst camera file)
    gt.txt                 TUM: t = frame / fps, camera pose in the model frame
    cMo/000000.txt         4x4 model-to-camera matrix per frame (row-major)
    clicks.txt             frame-0 clicks "X Y Z u v": visible model corners and their pixels
    model.obj              the object's triangles as rendered (full float64 precision)
    scene.ply              model + environment as one mesh (face property ``label``: 0 model,
                           1 floor/ground, 2 walls, 3 ceiling)
    scene.json             scenario, seed, all parameters: ``mst synth --from-scene`` reproduces
    frames.csv             per frame: t, model pixels, supersampled edge pixels

Scenarios: ``orbit`` (the camera circles the model, always looking at it, with height and roll
variation), ``corridor`` (walking past the model along a textured corridor; the camera turns away so
that the model leaves the view for the middle ~40% of the sequence and comes back), ``flyover``
(a UAV-like straight pass at ``distance`` metres above the model top, default clamp(0.3 x model
diagonal, 30, 150) m, at max(8, distance/4) m/s, looking at the model, pitched toward its facades),
``fast`` (any ``base`` scenario with only every ``drop``-th frame kept).

Colour noise (``rgb_noise`` sigma, 8-bit levels): per pixel and channel, the standardised sum of four
uniform random bytes (near-Gaussian, tails cut at 3.45 sigma), added before rounding to 8 bits.

Depth noise model (``depth_noise="kinect"``): axial noise sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m
(Nguyen, Izadi & Lovell 2012, Kinect v1), then disparity quantisation to 1/8 pixel with a 7.5 cm
baseline, holes at depth discontinuities (jump > 5% of z, grown by one pixel), at grazing angles
(> 80 deg from the normal), closer than 0.3 m, and 0.2% random dropouts. ``depth_noise="none"``
writes the exact z-depth of each pixel centre.
"""

from mst.core.poses import look_at
from mst.pipeline.synth.config import (
    BASE_SCENARIOS,
    CEILING,
    DEFAULT_FRAMES,
    DYNAMIC,
    FLOOR,
    MODEL,
    SCENARIOS,
    UP_AXES,
    WALL,
    SynthConfig,
)
from mst.pipeline.synth.core import SynthFrame, SynthPlan, SynthResult, plan_sequence, render_frame
from mst.pipeline.synth.runner import synthesize, synthesize_from_scene
from mst.pipeline.synth.scenarios import R_canon_from_up, Scene, focus_point
from mst.pipeline.synth.scene import (
    build_scene,
    choose_clicks,
    face_albedo,
    kinect_depth,
    load_model_triangles,
    model_corners,
    plane_ids,
)
from mst.pipeline.synth.writers import (
    _OWNED,
    SCENE_VERSION,
    _commit_out_dir,
    _prepare_out_dir,
    write_ply_mesh,
)

__all__ = ["BASE_SCENARIOS", "CEILING", "DEFAULT_FRAMES", "DYNAMIC", "FLOOR", "MODEL", "SCENARIOS", "SCENE_VERSION",
           "UP_AXES", "WALL", "R_canon_from_up", "Scene", "SynthConfig", "SynthFrame", "SynthPlan", "SynthResult",
           "_OWNED", "_commit_out_dir", "_prepare_out_dir", "build_scene", "choose_clicks", "face_albedo",
           "focus_point", "kinect_depth", "load_model_triangles", "look_at", "model_corners", "plan_sequence",
           "plane_ids", "render_frame", "synthesize", "synthesize_from_scene", "write_ply_mesh"]
