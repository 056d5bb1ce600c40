"""``mst init``: the first camera pose from clicked model points, or from GPS/attitude."""

from __future__ import annotations

import click

from mst import InputError, check_outputs
from mst.cli.common import (
    CONFIG_CLASSES,
    FINITE,
    build_config,
    config_options,
    emit_json,
    info,
    json_option,
    print_table,
    quiet_option,
    setup_logging,
    verbosity_options,
)

CONFIG_CLASSES["mst init"] = "mst.pipeline.init_pose:InitConfig"  # for --show-config


@click.command("init")
@click.option("--model", "model_path", required=True, type=click.Path(dir_okay=False), help="Polygon model (.cao .wrl .obj ...).")
@click.option("--camera", "camera_path", required=True, type=click.Path(dir_okay=False), help="Camera file (ViSP XML, OpenCV YAML/JSON, mst JSON).")
@click.option("--clicks", "clicks_path", type=click.Path(dir_okay=False), default=None,
              help="Clicks: 'X Y Z u v' per line, or 'u v' per line with --points.")
@click.option("--points", "points_path", type=click.Path(dir_okay=False), default=None,
              help="ViSP .init file (count, then 'X Y Z' lines) paired in order with 'u v' clicks.")
@click.option("--from-pose", "from_pose", nargs=6, type=FINITE, default=None, metavar="X Y Z YAW PITCH ROLL",
              help="Approximate pose: position (model frame, metres; x east, y north, z up) and yaw/pitch/roll (deg).")
@click.option("--mount", nargs=3, type=FINITE, default=None, metavar="YAW PITCH ROLL",
              help="Fixed camera-mount rotation relative to the vehicle body (deg), with --from-pose [default: 0 0 0].")
@click.option("--mount-offset", nargs=3, type=FINITE, default=None, metavar="DX DY DZ",
              help="Camera lever arm in the body frame (metres), with --from-pose [default: 0 0 0].")
@click.option("--from-nav", "from_nav", type=click.Path(dir_okay=False), default=None,
              help="Search the pose around a nav.csv row (GPS/AHRS, model frame = the log's frame) on --image; no clicks.")
@click.option("--nav-time", type=float, default=None, help="With --from-nav: the log time of the image [first fix].")
@click.option("--image", "image_path", type=click.Path(dir_okay=False), default=None,
              help="The frame the clicks were taken on (a picture, or a video: its first frame).")
@click.option("--overlay", "overlay_path", type=click.Path(dir_okay=False), default=None, help="PNG: the model drawn with the pose on --image.")
@click.option("--show-points", is_flag=True, help="Render the model with the --points numbered (needs --image and a pose/clicks, or -o picture).")
@click.option("--max-residual", type=FINITE, default=None,
              help="RMS reprojection error (px) above which init fails with a diagnosis [default: 4].")
@click.option("-o", "--output", "out", required=True, type=click.Path(dir_okay=False), help="Pose file (TUM line + cMo comment); with --show-points a PNG.")
@config_options()
@json_option
@quiet_option
@verbosity_options
def init_pose(model_path, camera_path, clicks_path, points_path, from_pose, mount, mount_offset, image_path,
              overlay_path, show_points, max_residual, out, config_file, set_values, as_json, quiet, verbose,
              from_nav=None, nav_time=None):
    """Compute the first camera pose from >= 4 clicked model points (PnP + robust refinement).

    Per-click reprojection residuals (px) are printed. When they are large the command fails
    and names the likely cause: two swapped clicks (and which), or a wrong camera.

    \b
    Examples:
      mst init --model teabox.cao --camera teabox.xml --clicks teabox.clicks --points teabox.init \\
               -o pose0.txt --image teabox.mp4 --overlay check.png
      mst init --model teabox.cao --camera teabox.xml --points teabox.init --show-points \\
               --image teabox.mp4 --clicks teabox.clicks -o where_to_click.png
      mst init --model bldg.obj --camera cam.json --from-pose 10 -40 30 90 -20 0 -o pose0.txt
      mst init --model bldg.obj --camera cam.json --from-nav nav.csv --mount 60 -20 0 --image f0.png -o pose0.txt

    \b
    --from-pose angles: yaw counter-clockwise from the model x axis (east) about z (up), pitch
    positive nose up, roll positive right side down; the body looks along its x axis. The camera
    looks along the body's forward axis after --mount (e.g. --mount 0 -90 0 for a nadir camera).
    Settings by name: --config init.yaml (max_residual_px, mount_ypr_deg, mount_offset_m, and the
    --from-nav search as auto.*, e.g. auto.n_coarse); the effective "config" is in --json.
    """
    from mst.pipeline.init_pose import InitConfig

    setup_logging(quiet, verbose, "mst init")
    cfg = build_config(InitConfig, config_file=config_file, set_values=set_values, section_name="init",
                       options={"max_residual_px": max_residual, "mount_ypr_deg": mount, "mount_offset_m": mount_offset},
                       flags={"max_residual_px": "--max-residual", "mount_ypr_deg": "--mount",
                              "mount_offset_m": "--mount-offset"})
    if overlay_path is not None and image_path is None:
        raise InputError(overlay_path, "--overlay needs --image (the frame to draw on)")
    if from_nav is not None:  # automatic initialisation (mst.pipeline.autoinit)
        from mst.pipeline.autoinit import run_autoinit

        if image_path is None:
            raise click.UsageError("--from-nav needs --image (the frame to search the model in)")
        res = run_autoinit(model_path, camera_path, out, from_nav, image_path, nav_time=nav_time,
                           overlay_path=overlay_path, cfg=cfg)
        info(f"edge score {res['score']:.3f} (guess {res['guess_score']:.3f}, {res['evaluated']} poses searched) -> {out}", quiet)
        if as_json:
            emit_json(res)
        return
    from mst.pipeline.init_pose import run_init

    check_outputs([out, overlay_path], [model_path, camera_path, clicks_path, points_path, image_path, config_file])
    if not show_points:
        if from_pose is not None and clicks_path:
            raise InputError(clicks_path, "give either --clicks or --from-pose, not both")
        if from_pose is None and not clicks_path:
            raise click.UsageError("give --clicks (with --points for 'u v' clicks) or --from-pose")
    res = run_init(model_path, camera_path, out, clicks_path=clicks_path, points_path=points_path,
                   from_pose=from_pose, image_path=image_path, overlay_path=overlay_path, show_points=show_points,
                   cfg=cfg)
    if res.get("residual_px") is not None:
        print_table("click residuals", ["#", "u", "v", "residual px"],
                    [(i + 1, f"{u:.1f}", f"{v:.1f}", f"{r:.2f}") for i, ((u, v), r) in enumerate(zip(res["uv"], res["residual_px"]))],
                    quiet)
        info(f"RMS {res['rms_px']:.2f} px -> {out}", quiet)
    else:
        info(f"-> {out}", quiet)
    if as_json:
        emit_json(res)
