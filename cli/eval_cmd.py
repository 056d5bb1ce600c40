"""``mst eval``: evaluation commands (``mst eval traj``: trajectory errors)."""

from __future__ import annotations

from pathlib import Path

import click

from mst import atomic_output, check_outputs
from mst.cli.common import (
    CONFIG_CLASSES,
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

CONFIG_CLASSES["mst eval traj"] = "mst.eval.traj.config:TrajConfig"  # for --show-config

#: TrajConfig field -> the option that sets it (errors on these fields name the option)
TRAJ_FLAGS = {"align": "--align", "t_max_diff_s": "--t-max-diff", "t_offset_s": "--t-offset",
              "delta_frames": "--delta", "delta_m": "--delta-m", "yaw_offset_deg": "--yaw-offset",
              "format": "--format", "csv_columns": "--csv-columns", "fps": "--fps"}


@click.group("eval")
def eval_group() -> None:
    """Evaluate results against references (trajectories).

    \b
    Example:
      mst eval traj traj.txt gt.txt --align se3
    """


@eval_group.command("traj")
@click.argument("estimate", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("reference", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--align", default=None, metavar="[none|se3|sim3|first]",
              help="Align the estimate onto the reference: Umeyama without/with scale, first pose, or none  "
              "[default: se3].")
@click.option("--t-max-diff", type=float, default=None,
              help="Association tolerance [s]: poses match when their timestamps differ by at most this  "
              "[default: 0.01].")
@click.option("--t-offset", type=float, default=None, help="Added to the estimate's timestamps [s]  [default: 0].")
@click.option("--delta", type=int, default=None, help="RPE step in frames  [default: 1].")
@click.option("--delta-m", type=float, default=None,
              help="RPE step in metres of travelled path  [default: 1].")
@click.option("--yaw-offset", type=float, default=None,
              help="Constant camera-mount yaw offset [deg] removed from d-yaw (est - ref - offset)  [default: 0].")
@click.option("--format", "fmt", default=None, metavar="[auto|tum|kitti|csv]",
              help="Trajectory file format (auto: .csv -> csv, 12 numbers per line -> kitti, else tum)  "
              "[default: auto].")
@click.option("--csv-columns", default=None, help="CSV column names, e.g. 't=time,x=east,y=north,z=up,qx=qx,qy=qy,"
              "qz=qz,qw=qw' (defaults: t x y z qx qy qz qw; no quaternion columns: positions only).")
@click.option("--fps", type=float, default=None, help="KITTI files: timestamps are line index / fps.")
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="PNG: top-down trajectories and dX dY dZ d-yaw over time with the gaps shaded.")
@click.option("--nav", "nav_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="GPS/AHRS log (nav.csv): also print the UAV table of vision, GPS/AHRS and ESTIMATE against REFERENCE.")
@click.option("--nav-calib", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="With --nav: the calibration JSON of `mst nav fuse --json` (model-to-world, mount, lever).")
@click.option("--nav-vision", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="With --nav: the vision trajectory (TUM) for the table's vision column.")
@config_options()
@json_option
@quiet_option
@verbosity_options
def traj(estimate, reference, align, t_max_diff, t_offset, delta, delta_m, yaw_offset, fmt, csv_columns, fps,
         plot, config_file, set_values, as_json, quiet, verbose, nav_path=None, nav_calib=None, nav_vision=None):
    """Compare an ESTIMATE trajectory with a REFERENCE (evo-compatible numbers).

    Associates poses by timestamp (nearest within --t-max-diff), aligns, and reports ATE
    (rmse/mean/median/std/min/max, metres), rotation error (deg), RPE per --delta frames and per
    --delta-m metres, the UAV table (mean and std of dX dY dZ [m] and d-yaw [deg]; yaw = heading
    of the camera's optical axis on the model XY plane) and the gaps (reference poses with no
    estimate: tracking lost). Files hold camera poses in model coordinates (TUM: t tx ty tz qx qy qz qw).

    \b
    Examples:
      mst eval traj traj.txt gt.txt --align se3
      mst eval traj traj.txt gt.txt --align sim3 --json
      mst eval traj traj.txt gps.csv --csv-columns t=time,x=e,y=n,z=h --align first --plot traj.png
      mst eval traj traj.txt gt.txt --yaw-offset 90 --t-max-diff 0.02
      mst eval traj fused.txt gt.txt --nav nav.csv --nav-calib fused.json --nav-vision traj.txt
      mst eval traj traj.txt gt.txt --config eval.yaml --set delta_m=5

    Settings (--config FILE, --set KEY=VALUE; the options above override them): align,
    t_max_diff_s, t_offset_s, delta_frames, delta_m, yaw_offset_deg, format, csv_columns, fps
    (--show-config lists them); the "config" block of --json is the effective set.
    """
    from mst.eval.traj import TrajConfig, evaluate_trajectories, report_rows, uav_rows

    setup_logging(quiet, verbose, prog="mst eval traj")
    cfg = build_config(TrajConfig, config_file=config_file, set_values=set_values, section_name="eval_traj",
                       flags=TRAJ_FLAGS,
                       options={"align": align, "t_max_diff_s": t_max_diff, "t_offset_s": t_offset,
                                "delta_frames": delta, "delta_m": delta_m, "yaw_offset_deg": yaw_offset,
                                "format": fmt, "csv_columns": csv_columns, "fps": fps})
    check_outputs([plot], [estimate, reference])
    result = evaluate_trajectories(estimate, reference, cfg)
    series = result.series
    s = result.to_json()
    if plot is not None:
        from mst.eval.plots import trajectory_figure

        gaps = [(g["t_start"], g["t_end"]) for g in s["gaps"]["ranges"]]
        with atomic_output(plot) as tmp:
            trajectory_figure(tmp, series.t_ref_all, series.xyz_ref_all, series.t, series.xyz_est,
                              series.dxyz, series.dyaw, gaps,
                              title=f"{Path(estimate).name} vs {Path(reference).name} (align {cfg.align})")
    if not quiet:
        print_table("trajectory errors", ["metric", "value"],
                    [[a.replace("[", "\\["), b] for a, b in report_rows(s)])
        print_table("UAV table (estimate - reference)", ["", "mean", "std"],
                    [[a.replace("[", "\\["), b, c] for a, b, c in uav_rows(s)])
        if s["gaps"]["count"]:
            info("gaps: " + ", ".join(f"frames {g['first']}-{g['last']} ({g['t_start']:.3f}-{g['t_end']:.3f} s)"
                                      for g in s["gaps"]["ranges"][:20])
                 + (" ..." if s["gaps"]["count"] > 20 else ""))
    if nav_path is not None:  # the UAV table against a navigation log (mst.eval.traj.navtable)
        from mst.eval.traj.navtable import nav_table_from_files

        nt = nav_table_from_files(estimate, reference, nav_path, nav_calib, nav_vision, cfg.t_max_diff_s)
        s["nav_table"] = nt.to_json()
        if not quiet:
            print_table(f"UAV table against {Path(reference).name} (mean ± std)", ["", *nt.columns],
                        [[r[0].replace("[", "\\["), *r[1:]] for r in nt.rows()])
    if as_json:
        emit_json(s)
