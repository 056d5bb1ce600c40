"""``mst refine``: offline global refinement of a tracked trajectory against the model (depth ICP +
keyframe pose graph)."""

from __future__ import annotations

import click

from mst.cli.common import (
    CONFIG_CLASSES,
    FINITE,
    build_config,
    config_options,
    emit_json,
    info,
    json_option,
    quiet_option,
    setup_logging,
    verbosity_options,
)

CONFIG_CLASSES["mst refine"] = "mst.pipeline.refine.config:RefineConfig"  # for --show-config

FLAGS = {"fps": "--fps", "keyframe_every": "--keyframe-every", "rounds": "--rounds", "depth.scale": "--depth-scale"}


@click.command("refine")
@click.option("--traj", "traj", type=click.Path(dir_okay=False), required=True,
              help="TUM trajectory to refine (T_model_cam per frame, e.g. mst track's traj.txt).")
@click.option("--model", "model", type=click.Path(dir_okay=False), required=True,
              help="The model (.wrl, .cao, .obj, .ply, ...), metres, model frame.")
@click.option("--camera", "camera", type=click.Path(dir_okay=False), required=True,
              help="Depth camera file (mst JSON, ViSP XML, OpenCV YAML); depth registered to the tracked camera.")
@click.option("--depth", "depth", required=True, help="Folder (or quoted glob) of depth frames, frame k = pose time k "
                                                      "(or round(t * FPS) with --fps).")
@click.option("-o", "--output", "output", type=click.Path(dir_okay=False), required=True,
              help="Refined TUM trajectory (same times as --traj).")
@click.option("--gt", "gt", type=click.Path(dir_okay=False), default=None,
              help="Ground-truth TUM trajectory: report the ATE (position RMSE, model frame) before/after.")
@click.option("--frames", "frames", default=None,
              help="The tracked images (folder, video, glob): bundle adjustment of the keyframes with KLT tie "
                   "points first (--set ba=false: off).")
@click.option("--cov", "cov", type=click.Path(dir_okay=False), default=None,
              help="mst track's pose covariances, the BA priors [default: traj.cov.csv beside --traj when present].")
@click.option("--nav", "nav", type=click.Path(dir_okay=False), default=None,
              help="GPS/AHRS log (nav.csv): GPS (Huber) and AHRS factors in the bundle adjustment, calibrated as "
                   "by mst nav fuse (settings: nav.*).")
@click.option("--model-to-world", "m2w", type=click.Path(dir_okay=False), default=None,
              help="4x4 model-to-world transform for --nav (default: estimated from the log, as mst nav fuse).")
@click.option("--fps", type=FINITE, default=None, help="Trajectory times are seconds: frame index = round(t * FPS).")
@click.option("--keyframe-every", type=int, default=None, help="Every N-th pose is a keyframe [default: 5].")
@click.option("--rounds", type=int, default=None, help="At most this many rounds [default: 4].")
@click.option("--depth-scale", type=FINITE, default=None, help="Integer depth units per metre [default: 1000].")
@config_options()
@json_option
@quiet_option
@verbosity_options
def refine(traj, model, camera, depth, output, gt, frames, cov, nav, m2w, fps, keyframe_every, rounds, depth_scale, config_file, set_values,
           as_json, quiet, verbose):
    """Refine a tracked trajectory globally against the model with the depth frames.

    Every N-th pose is a keyframe; its depth samples (a pixel grid) are placed with its pose. With
    --frames, first a bundle adjustment of the keyframes: KLT corners tracked keyframe to keyframe
    as tie points (started from the depth), the tracked poses as priors with W = JᵀJ (mst track's
    traj.cov.csv), and with --nav the GPS fixes (Huber) and AHRS attitudes through the mount
    calibrated as mst nav fuse does; its relative motions are the ones the pose graph keeps. Each
    round: (1) robust point-to-plane ICP (Open3D, Tukey kernel) of the fused keyframe cloud onto
    the model's sampled surface, applied as one rigid correction; (2) per keyframe the same ICP
    of its own samples, a prior with the information JᵀJ of its point-to-plane residuals (frames
    that do not see the model get none); (3) a pose graph over the keyframes (the priors, and the
    tracked relative motions between consecutive keyframes as between-factors), solved by sparse
    least squares. Rounds repeat while the mean cloud-to-model distance drops; a round that does
    not lower it is discarded. The correction of every other pose is interpolated between its
    keyframes. The model-frame position is the reference: no alignment.

    \b
    Examples:
      mst refine --traj traj.txt --model seq/model.obj --camera seq/camera.json --depth seq/depth \\
                 --fps 30 -o refined.txt --gt seq/gt.txt --json
      mst refine --traj traj.txt --model bldg.wrl --camera cam.json --depth depth/ -o refined.txt --set pixel_step=2

    \b
    Output: TUM (metres, model frame), same times. Summary on stderr; --json on stdout with the C2M
    statistics (mean/median/rms/p95, m) before and after, the ATE with --gt, and the effective "config".
    """
    from mst import check_outputs
    from mst.pipeline.depth_io import DEPTH_SUFFIXES
    from mst.pipeline.refine import RefineConfig
    from mst.pipeline.refine import refine as run_refine

    setup_logging(quiet, verbose, "mst refine")
    check_outputs([output], [traj, model, camera, gt, cov, nav, m2w, frames, config_file, (depth, DEPTH_SUFFIXES)])
    cfg = build_config(RefineConfig, config_file=config_file, set_values=set_values, section_name="refine",
                       options={"fps": fps, "keyframe_every": keyframe_every, "rounds": rounds,
                                "depth.scale": depth_scale}, flags=FLAGS)
    s = run_refine(traj, model, camera, depth, output, cfg, gt_path=gt, frames_path=frames, nav_path=nav, cov_path=cov,
                   m2w_path=m2w)
    b, a = s.c2m_before, s.c2m_after
    info(f"{s.keyframes} keyframes ({s.priors} see the model), {s.rounds_kept}/{s.rounds} rounds kept; mean C2M "
         f"{b.mean_m:.4g} -> {a.mean_m:.4g} m over {b.points:,} samples near the model", quiet)
    if s.ba.get("points"):
        info(f"bundle adjustment: {s.ba['points']} tie points, {s.ba['observations']} observations, reprojection RMS "
             f"{s.ba['reproj_rms_before_px']:.3g} -> {s.ba['reproj_rms_after_px']:.3g} px", quiet)
    if s.ate:
        ba = f", {s.ate['after_ba_m']:.4g} m after the bundle adjustment" if "after_ba_m" in s.ate else ""
        info(f"ATE {s.ate['before_m']:.4g} -> {s.ate['after_m']:.4g} m ({s.ate['matched']} poses{ba})", quiet)
    info(f"wrote {s.poses} poses to {output} in {s.elapsed_s:.2f} s", quiet)
    if as_json:
        emit_json(s.to_json())
