"""``mst track``: model-based edge tracking through a video or an image sequence."""

from __future__ import annotations

import click

from mst import check_outputs
from mst.cli.common import (
    CONFIG_CLASSES,
    POSITIVE,
    config_options,
    emit_json,
    info,
    json_option,
    progress_bar,
    quiet_option,
    setup_logging,
    verbosity_options,
)

#: config field -> the option that sets it (errors on these fields name the option)
FLAGS = {"edges.search_range_px": "--range", "edges.sample_step_px": "--step", "edges.pyramid_levels": "--pyramid",
         "edges.constant_velocity": "--constant-velocity", "use_klt": "--klt", "relocalise": "--relocalise",
         "aid": "--slam", "edge_source": "--edges", "depth.scale": "--depth-scale"}
CONFIG_CLASSES["mst track"] = "mst.pipeline.tracking.config:TrackConfig"  # --show-config


@click.command("track")
@click.argument("frames_src", metavar="FRAMES")
@click.option("--model", "model_path", required=True, type=click.Path(dir_okay=False), help="Polygon model (.cao .wrl .obj ...), metres.")
@click.option("--camera", "camera_path", required=True, type=click.Path(dir_okay=False), help="Camera file (ViSP XML, OpenCV YAML/JSON, mst JSON).")
@click.option("--init", "init_path", required=True, type=click.Path(dir_okay=False), help="Pose of the first frame (TUM line or 4x4 cMo), e.g. from `mst init`.")
@click.option("-o", "--output", "out", required=True, type=click.Path(dir_okay=False), help="Trajectory (TUM, tracked frames only); .csv/.json beside it.")
@click.option("--settings", "settings_path", type=click.Path(dir_okay=False), default=None,
              help="ViSP tracker XML (<conf><ecm>..); default: the camera file when it is one, else built-in defaults.")
@click.option("--frames", "frame_range", default=None, help="Frame selection a:b:step (b exclusive).")
@click.option("--scale", type=POSITIVE, default=1.0, show_default=True, help="Resize frames by this factor (intrinsics follow).")
@click.option("--fps", type=POSITIVE, default=None, help="Frame rate for time stamps (default: the video's; image sequences: t = index).")
@click.option("--range", "search_range", type=int, default=None, help="Moving-edge search range, px each side (edges.search_range_px; overrides settings).")
@click.option("--step", "sample_step", type=float, default=None, help="Sample step along edges, px (edges.sample_step_px; overrides settings).")
@click.option("--pyramid", "pyramid_levels", type=int, default=None, help="Coarse-to-fine levels (1 = none, 2 = half resolution first).")
@click.option("--constant-velocity", is_flag=True, default=None, help="Predict each pose by repeating the last motion (no SLAM aid).")
@click.option("--klt/--no-klt", default=None,
              help="Add KLT points inside visible faces (ViSP hybrid tracker); default: on with --slam auto without --depth, else off.")
@click.option("--relocalise/--no-relocalise", default=None,
              help="Learn the object's keypoints while tracked and re-acquire a lost pose without clicks (status relocalised; default: on).")
@click.option("--overlay", default=None, type=click.Path(), help="Write an overlay video (.mp4) or a folder of PNGs.")
@click.option("--slam", type=click.Choice(["auto", "mono", "rgbd", "off"]), default=None,
              help="SLAM aid (default auto): auto = rgbd with --depth, else edges + KLT with the mono aid switched on only when the edges weaken; off = edges only.")
@click.option("--depth", "depth_dir", type=click.Path(file_okay=False), default=None, help="Depth frames folder (for --slam rgbd).")
@click.option("--depth-scale", type=POSITIVE, default=None,
              help="Raw depth units per metre of 16-bit depth frames (default 1000 = mm; TUM RGB-D: 5000).")
@click.option("--depth-camera", "depth_camera", type=click.Path(dir_okay=False), default=None, help="Depth camera file (default: the colour camera).")
@click.option("--landmarks", "landmarks_path", type=click.Path(dir_okay=False), default=None,
              help="Write the SLAM map points (model frame) as PLY, e.g. for `mst fuse --landmarks` (mono).")
@click.option("--depth-to-color", "depth_to_color", type=click.Path(dir_okay=False), default=None, help="4x4 depth-to-colour transform file.")
@click.option("--edges", type=click.Choice(["auto", "polygon", "render"]), default=None,
              help="Edges to track (default auto): polygon = the model's polygon edges; render = contours and creases from CPU renders "
                   "of the mesh (curved objects, raw TINs); auto = polygon for .cao/.wrl and small planar meshes, "
                   "the polygon edges of its planar faces (merged) for a closed polyhedral triangle mesh with many "
                   "faces (a box or building TIN), render for curved or open triangle meshes with many faces and "
                   "for a .cao with cylinders (their limbs and end rims come from the render).")
@config_options(presets=True)
@json_option
@quiet_option
@verbosity_options
def track(frames_src, model_path, camera_path, init_path, out, settings_path, frame_range, scale, fps, search_range,
          sample_step, pyramid_levels, constant_velocity, klt, relocalise, overlay, slam, depth_dir, depth_scale, depth_camera,
          depth_to_color, landmarks_path, edges, config_file, set_values, preset, as_json, quiet, verbose):
    """Track MODEL through FRAMES (video, image folder, glob or printf pattern) from an initial pose.

    Per frame: visible model edges are sampled, moving edges searched along their normals (ViSP's
    oriented masks and contrast test), and the pose found by robust virtual visual servoing (Tukey
    IRLS + Levenberg-Marquardt). A frame whose edges do not support the pose is marked `lost` (not
    written to the trajectory); tracking restarts from the last good pose with a wider search.

    \b
    Example:
      mst init --model teabox.cao --camera teabox.xml --clicks teabox.clicks --points teabox.init -o pose0.txt
      mst track teabox.mp4 --model teabox.cao --camera teabox.xml --init pose0.txt -o traj.txt --overlay ov.mp4

    \b
    Outputs: traj.txt (TUM: t tx ty tz qx qy qz qw, camera pose in the model frame, tracked frames
    only), traj.csv (frame, time, status, samples, inliers, residual_px, health = mean gradient /
    model-normal angle in degrees, ms, score = calibrated health score: 1 typical, <= 0 rejected,
    aid = SLAM aid on/standby, reason = why the edge pose was not used), traj.cov.csv (per output
    frame the 6x6 pose covariance: the edge fit's, or a slam frame's propagated drift covariance;
    and the camera-position / rotation 1-sigma), traj.json with --json
    (also printed on stdout).
    """
    from pathlib import Path

    from mst.cli.common import build_config
    from mst.errors import ConfigError
    from mst.pipeline.depth_io import DEPTH_SUFFIXES, IMAGE_SUFFIXES
    from mst.pipeline.tracking.config import TrackConfig, visp_xml_settings
    from mst.pipeline.tracking.runner import run_track

    setup_logging(quiet, verbose, "mst track")
    out_p = Path(out)
    frames_p = Path(frames_src)
    # the trajectory, its side outputs (traj.csv, traj.json) and the others must not replace an input
    check_outputs([out_p, out_p.with_suffix(".csv"), out_p.with_suffix(".cov.csv"),
                   out_p.with_suffix(".json") if as_json else None, landmarks_path,
                   overlay],
                  [(frames_p, IMAGE_SUFFIXES) if frames_p.is_dir() else frames_p if frames_p.exists() else None,
                   model_path, camera_path, init_path, settings_path, depth_camera, depth_to_color,
                   (depth_dir, DEPTH_SUFFIXES) if depth_dir else None, config_file])
    # a ViSP tracker XML (--settings, or the camera file when it is one): the base layer
    xml = settings_path or (camera_path if Path(camera_path).is_file()
                            and "<ecm>" in Path(camera_path).read_text(errors="replace") else None)
    base = visp_xml_settings(xml) if xml else None
    options = {"edges.search_range_px": search_range, "edges.sample_step_px": sample_step,
               "edges.pyramid_levels": pyramid_levels, "edges.constant_velocity": constant_velocity, "use_klt": klt,
               "relocalise": relocalise, "aid": slam, "edge_source": edges, "depth.scale": depth_scale}
    cfg = build_config(TrackConfig, config_file=config_file, set_values=set_values, preset=preset, options=options,
                       flags=FLAGS, section_name="track", base=base)
    try:
        summary = run_track(frames_src, model_path, camera_path, init_path, out, cfg, frames=frame_range, scale=scale,
                            fps=fps, overlay=overlay, depth_dir=depth_dir, depth_camera_path=depth_camera,
                            depth_to_color_path=depth_to_color, landmarks_path=landmarks_path, write_json=as_json,
                            progress=lambda total: progress_bar(total, "tracking", quiet))
    except ConfigError as e:
        raise _named(e, xml, base or {}, options) from None
    res = summary.mean_residual_px
    sc = summary.status_counts
    wakes = summary.optional.get("aid_wakes")
    info(f"tracked {summary.tracked}/{summary.frames} frames (model {sc['model']}, slam {sc['slam']}, relocalised "
         f"{sc['relocalised']}, lost {sc['lost']}; {summary.health_score_rejects} edge poses rejected by the health "
         f"score" + (f"; SLAM aid switched on {wakes}x" if wakes else "") + "), median "
         f"{summary.median_ms:.1f} ms/frame, mean residual {'-' if res is None else f'{res:.2f}'} px -> {out}", quiet)
    why = withheld_line(summary.optional, sc["lost"], cfg.slam.drift_budget_rel, cfg.slam.drift_budget_deg)
    if why:
        info(why, quiet)
    if as_json:
        emit_json(summary.to_json())


def withheld_line(optional: dict, n_lost: int, budget_rel: float, budget_deg: float) -> str:
    """The lost frames that the error budgets and the image checks withheld (a pose existed, but it was
    not certain or not supported enough to be output), by cause, for the summary; empty when none.
    ``optional``: the run's ``TrackSummary.optional`` (its ``*_frames`` lists)."""
    causes = (("drift_budget_frames", f"map poses beyond the drift budget (2 sigma over {budget_rel * 100:g} % of the "
                                      f"distance or {budget_deg:g} deg: slam.drift_budget_rel/_deg)"),
              ("pose_budget_frames", "edge poses beyond the same error budget"),
              ("ambiguous_frames", "ambiguous edge poses (another fit of the image beyond the budget)"),
              ("map_refuted_frames", "map poses refuted by the image"))
    parts = [f"{len(set(optional[k]))} {text}" for k, text in causes if optional.get(k)]
    return f"of the {n_lost} lost frames, withheld: " + "; ".join(parts) if parts and n_lost else ""


def _named(e, xml, base: dict, options: dict):
    """A library ConfigError raised while tracking, named as the user set it: the option, the ViSP
    tag of the settings file, or the dotted field (a config file, --set, a default)."""
    from mst import InputError
    from mst.pipeline.tracking.config import TAG_OF

    if e.field in base and e.source is None and options.get(e.field) is None:
        tag = "<" + TAG_OF[e.field].strip("<>").split("/")[-1] + ">"
        return InputError(xml, e.problem.replace("this setting", tag))
    if e.field in FLAGS and e.source is None and options.get(e.field) is not None:
        return InputError(None, f"{FLAGS[e.field]}: {e.problem}")
    return e
