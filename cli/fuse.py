"""``mst fuse``: depth frames + trajectory -> point cloud in model coordinates."""

from __future__ import annotations

import click

from mst import check_outputs
from mst.cli.common import (
    NON_NEGATIVE,
    POSITIVE,
    FiniteFloat,
    emit_json,
    info,
    json_option,
    progress_bar,
    quiet_option,
)


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
@click.option("--depth-scale", type=POSITIVE, default=1000.0, show_default=True,
              help="Integer depth units per metre (1000 = mm, 5000 = TUM RGB-D); a value < 1 is metres per unit.")
@click.option("--min-depth", type=NON_NEGATIVE, default=0.1, show_default=True, help="Metres; nearer samples are dropped.")
@click.option("--max-depth", type=FiniteFloat(min=0, min_open=True, allow_inf=True), default=50.0, show_default=True, help="Metres; farther samples are dropped (inf: no limit).")
@click.option("--edge-k", type=NON_NEGATIVE, default=0.03, show_default=True,
              help="Drop pixels whose 4-neighbour depth jumps by more than K * depth (0: off).")
@click.option("--max-angle", type=FiniteFloat(min=0, min_open=True, max=90), default=80.0, show_default=True,
              help="Degrees; drop samples seen more obliquely than this to their surface (90: off).")
@click.option("--smooth", type=click.IntRange(min=0, max=99), default=0, show_default=True,
              help="Bilateral filter diameter in pixels for noisy depth (edge-preserving, on log-depth; 0: off).")
@click.option("--smooth-rel", type=POSITIVE, default=0.02, show_default=True,
              help="Bilateral range sigma as a fraction of depth.")
@click.option("--voxel", type=NON_NEGATIVE, default=None,
              help="Voxel size in metres: one averaged point per voxel, 0 keeps every sample [default: 0.005]; "
                   "with --tsdf the TSDF voxel [default: 0.01].")
@click.option("--stride", type=click.IntRange(min=1), default=1, show_default=True, help="Fuse every N-th depth frame.")
@click.option("--fps", type=POSITIVE, default=None,
              help="Trajectory times are seconds: frame index = round(t * FPS). Default: times are frame indices.")
@click.option("--tsdf", is_flag=True, help="Fuse a TSDF (Open3D VoxelBlockGrid) and output its surface points.")
@click.option("--color", "color", default=None, help="Folder of colour images (same frame order) to colour the points.")
@click.option("--color-camera", type=click.Path(dir_okay=False), default=None,
              help="Colour camera file (needed with --depth-to-color; default: the depth camera).")
@click.option("--landmarks", type=click.Path(dir_okay=False), default=None,
              help="PLY of model-frame points to add (e.g. the mono SLAM map of `mst track --slam mono --landmarks`).")
@json_option
@quiet_option
def fuse(traj, depth, camera, output, depth_to_color, depth_scale, min_depth, max_depth, edge_k, max_angle, smooth,
         smooth_rel, voxel,
         stride, fps, tsdf, color, color_camera, landmarks, as_json, quiet):
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
    Summary on stderr, --json on stdout.
    """
    from mst.pipeline.fusion import FuseConfig
    from mst.pipeline.fusion import fuse as run_fuse

    if depth is not None and (traj is None or camera is None):
        raise click.UsageError("--depth needs --traj and --camera")
    if depth is None and landmarks is None:
        raise click.UsageError("give --depth (with --traj and --camera) or --landmarks")
    if min_depth >= max_depth:
        raise click.BadParameter(f"{max_depth:g} m is not beyond --min-depth {min_depth:g} m", param_hint="--max-depth")
    from mst.pipeline.depth_io import DEPTH_SUFFIXES, IMAGE_SUFFIXES

    check_outputs([output], [traj, camera, depth_to_color, color_camera, landmarks,
                             (depth, DEPTH_SUFFIXES) if depth is not None else None,
                             (color, IMAGE_SUFFIXES) if color is not None else None])
    if voxel is None:
        voxel = 0.01 if tsdf else 0.005
    cfg = FuseConfig(depth_scale=depth_scale, min_depth=min_depth, max_depth=max_depth, edge_k=edge_k,
                     max_angle_deg=max_angle, smooth_px=smooth, smooth_rel=smooth_rel, voxel=voxel, stride=stride,
                     fps=fps, tsdf=tsdf)
    summary = run_fuse(output, cfg, traj_path=traj, depth_dir=depth, camera_path=camera,
                       depth_to_color_path=depth_to_color, color_dir=color, color_camera_path=color_camera,
                       landmarks_path=landmarks, progress=lambda n: progress_bar(n, "fuse", quiet))
    s = summary
    if depth is not None:
        info(f"fused {s['fused_frames']}/{s['frames']} frames ({s['skipped_no_pose']} without a pose, "
             f"{s['skipped_stride']} skipped by stride, {s['empty_frames']} empty); "
             f"{s['points_fused']:,} of {s['samples']:,} samples kept (range -{s['dropped_range']:,}, "
             f"edges -{s['dropped_edge']:,}, grazing -{s['dropped_grazing']:,})", quiet)
        if s["poses_without_frame"]:
            info(f"warning: {s['poses_without_frame']} pose(s) point past the last of {s['frames']} depth frames "
                 "(wrong --fps, or a trajectory of another sequence?)", quiet)
    if s["landmarks"]:
        info(f"added {s['landmarks']:,} landmarks", quiet)
    info(f"wrote {s['points_out']:,} points ({s['mode']}) to {output} in {s['elapsed_s']:.2f} s "
         f"({s['frames_per_s']:.1f} frames/s)", quiet)
    if s.get("warning"):
        info(f"warning: {s['warning']}", quiet)
    if as_json:
        emit_json(summary)
