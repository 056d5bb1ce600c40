"""``mst fuse``: depth frames + trajectory -> point cloud in model coordinates."""

from __future__ import annotations

import click

from mst import check_outputs
from mst.cli.common import (
    CONFIG_CLASSES,
    FINITE,
    FiniteFloat,
    build_config,
    config_options,
    emit_json,
    info,
    json_option,
    progress_bar,
    quiet_option,
    setup_logging,
    verbosity_options,
)

CONFIG_CLASSES["mst fuse"] = "mst.pipeline.fusion.config:FuseConfig"  # for --show-config

#: config field -> the option that sets it (a bad value is reported under the option's name)
FLAGS = {"depth.scale": "--depth-scale", "depth.min_m": "--min-depth", "depth.max_m": "--max-depth",
         "depth.edge_rel": "--edge-k", "max_angle_deg": "--max-angle", "smooth_px": "--smooth",
         "smooth_rel": "--smooth-rel", "voxel_m": "--voxel", "tsdf_voxel_m": "--voxel", "stride": "--stride",
         "fps": "--fps"}


@click.command("fuse")
@click.option("--traj", "traj", type=click.Path(dir_okay=False), default=None,
              help="TUM trajectory: camera pose in model frame per frame (lost frames absent).")
@click.option("--depth", "depth", default=None,
              help="Folder (or quoted glob) of depth frames: 16-bit PNG/TIFF, .npy, .exr, ViSP .bin.")
@click.option("--camera", "camera", type=click.Path(dir_okay=False), default=None,
              help="Depth camera file (mst JSON, ViSP XML, OpenCV YAML); size taken from the frames if absent.")
@click.option("-o", "--output", "output", type=click.Path(dir_okay=False), required=True,
              help="Output cloud, binary PLY (x y z double, metres, model frame).")
@click.option("--depth-to-color", "depth_to_color", type=click.Path(dir_okay=False), default=None,
              help="4x4 T_depth_color (ViSP's depth_M_color.txt: X_depth = T @ X_color); the trajectory is then "
                   "the COLOUR camera's.")
@click.option("--depth-scale", type=FINITE, default=None,
              help="Integer depth units per metre (1000 = mm, 5000 = TUM RGB-D); a value < 1 is metres per unit "
                   "[default: 1000; config depth.scale].")
@click.option("--min-depth", type=FINITE, default=None, help="Metres; nearer samples are dropped [default: 0.1; depth.min_m].")
@click.option("--max-depth", type=FiniteFloat(allow_inf=True), default=None,
              help="Metres; farther samples are dropped (inf: no limit) [default: 50; depth.max_m].")
@click.option("--edge-k", type=FINITE, default=None,
              help="Drop pixels whose 4-neighbour depth jumps by more than K * depth (0: off) [default: 0.03; depth.edge_rel].")
@click.option("--max-angle", type=FINITE, default=None,
              help="Degrees; drop samples seen more obliquely than this to their surface (90: off) [default: 80].")
@click.option("--smooth", type=int, default=None,
              help="Bilateral filter diameter in pixels for noisy depth (edge-preserving, on log-depth; 0: off) [default: 0].")
@click.option("--smooth-rel", type=FINITE, default=None, help="Bilateral range sigma as a fraction of depth [default: 0.02].")
@click.option("--voxel", type=FINITE, default=None,
              help="Voxel size in metres: one averaged point per voxel, 0 keeps every sample [default: 0.005, voxel_m]; "
                   "with --tsdf the TSDF voxel [default: 0.01, tsdf_voxel_m].")
@click.option("--stride", type=int, default=None, help="Fuse every N-th depth frame [default: 1].")
@click.option("--fps", type=FINITE, default=None,
              help="Trajectory times are seconds: frame index = round(t * FPS). Default: times are frame indices.")
@click.option("--tsdf", is_flag=True, default=None, help="Fuse a TSDF (Open3D VoxelBlockGrid) and output its surface points.")
@click.option("--color", "color", default=None, help="Folder of colour images (same frame order) to colour the points.")
@click.option("--color-camera", type=click.Path(dir_okay=False), default=None,
              help="Colour camera file (needed with --depth-to-color; default: the depth camera).")
@click.option("--landmarks", type=click.Path(dir_okay=False), default=None,
              help="PLY of model-frame points to add (e.g. the mono SLAM map of `mst track --slam mono --landmarks`).")
@config_options()
@json_option
@quiet_option
@verbosity_options
def fuse(traj, depth, camera, output, depth_to_color, depth_scale, min_depth, max_depth, edge_k, max_angle, smooth,
         smooth_rel, voxel, stride, fps, tsdf, color, color_camera, landmarks, config_file, set_values, as_json, quiet,
         verbose):
    """Fuse depth frames into one point cloud in model coordinates.

    Each depth frame k is back-projected with the pose of frame k (time t = k, or t * FPS = k
    with --fps) and filtered (depth range, discontinuities, grazing angles). Frames with no pose
    (lost) are skipped and counted. Memory is bounded by the output cloud: points are merged into
    a voxel grid (--voxel) or a TSDF (--tsdf) frame by frame. For noisy depth (Kinect-like,
    about 1 cm at 2.5 m) add --smooth 5 (per-frame bilateral filter) or use --tsdf.

    \b
    Examples:
      mst fuse --traj traj.txt --depth seq/depth --camera seq/camera.json --voxel 0.01 -o cloud.ply
      mst fuse --traj seq/gt.txt --fps 30 --depth seq/depth --camera seq/camera.json --tsdf -o surf.ply
      mst fuse --traj traj.txt --depth seq/depth --camera seq/camera.json --smooth 5 --voxel 0.01 -o cloud.ply
      mst fuse --traj traj.txt --depth cube/ --camera cube/model/cube_depth.xml \\
               --depth-to-color cube/depth_M_color.txt -o cube.ply
      mst fuse --landmarks map.ply -o cloud.ply      # mono: the SLAM map written by
                                                     # mst track --slam mono --landmarks map.ply

    \b
    Output: binary PLY, x y z double (metres), red green blue uchar with --color (black where
    no colour image saw the point), count uint (samples merged per point; not with --tsdf).
    Summary on stderr, --json on stdout (with the effective "config": give it back with --config
    to repeat the run; --set depth.scale=5000 sets one setting by name).
    """
    from mst.pipeline.fusion import FuseConfig
    from mst.pipeline.fusion import fuse as run_fuse

    setup_logging(quiet, verbose, "mst fuse")
    if depth is not None and (traj is None or camera is None):
        raise click.UsageError("--depth needs --traj and --camera")
    if depth is None and landmarks is None:
        raise click.UsageError("give --depth (with --traj and --camera) or --landmarks")
    from mst.pipeline.depth_io import DEPTH_SUFFIXES, IMAGE_SUFFIXES

    check_outputs([output], [traj, camera, depth_to_color, color_camera, landmarks, config_file,
                             (depth, DEPTH_SUFFIXES) if depth is not None else None,
                             (color, IMAGE_SUFFIXES) if color is not None else None])
    # --voxel is the grid of the chosen mode (a TSDF's --voxel 0 keeps the TSDF default, as it always did)
    grid = {"tsdf_voxel_m": voxel or None} if tsdf else {"voxel_m": voxel}
    cfg = build_config(FuseConfig, config_file=config_file, set_values=set_values, section_name="fuse",
                       options={"depth.scale": depth_scale, "depth.min_m": min_depth, "depth.max_m": max_depth,
                                "depth.edge_rel": edge_k, "max_angle_deg": max_angle, "smooth_px": smooth,
                                "smooth_rel": smooth_rel, "stride": stride, "fps": fps, "tsdf": tsdf, **grid},
                       flags=FLAGS)
    summary = run_fuse(output, cfg, traj_path=traj, depth_dir=depth, camera_path=camera,
                       depth_to_color_path=depth_to_color, color_dir=color, color_camera_path=color_camera,
                       landmarks_path=landmarks, progress=lambda n: progress_bar(n, "fuse", quiet))
    s = summary
    if depth is not None:
        info(f"fused {s['fused_frames']}/{s['frames']} frames ({s['skipped_no_pose']} without a pose, "
             f"{s['skipped_stride']} skipped by stride, {s['empty_frames']} empty); "
             f"{s['points_fused']:,} of {s['samples']:,} samples kept (range -{s['dropped_range']:,}, "
             f"edges -{s['dropped_edge']:,}, grazing -{s['dropped_grazing']:,})", quiet)
    if s["landmarks"]:
        info(f"added {s['landmarks']:,} landmarks", quiet)
    info(f"wrote {s['points_out']:,} points ({s['mode']}) to {output} in {s['elapsed_s']:.2f} s "
         f"({s['frames_per_s']:.1f} frames/s)", quiet)
    if as_json:
        emit_json(summary)
