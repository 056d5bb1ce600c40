"""``mst eval``: evaluation commands (``mst eval traj``: trajectory errors)."""

from __future__ import annotations

from pathlib import Path

import click

from mst import atomic_output, check_outputs
from mst.cli.common import (
    FINITE,
    NON_NEGATIVE,
    POSITIVE,
    emit_json,
    info,
    json_option,
    print_table,
    quiet_option,
)


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
@click.option("--align", type=click.Choice(["none", "se3", "sim3", "first"]), default="se3", show_default=True,
              help="Align the estimate onto the reference: Umeyama without/with scale, first pose, or none.")
@click.option("--t-max-diff", type=NON_NEGATIVE, default=0.01, show_default=True,
              help="Association tolerance [s]: poses match when their timestamps differ by at most this.")
@click.option("--t-offset", type=FINITE, default=0.0, show_default=True, help="Added to the estimate's timestamps [s].")
@click.option("--delta", type=click.IntRange(min=1), default=1, show_default=True, help="RPE step in frames.")
@click.option("--delta-m", type=POSITIVE, default=1.0, show_default=True,
              help="RPE step in metres of travelled path.")
@click.option("--yaw-offset", type=FINITE, default=0.0, show_default=True,
              help="Constant camera-mount yaw offset [deg] removed from d-yaw (est - ref - offset).")
@click.option("--format", "fmt", type=click.Choice(["auto", "tum", "kitti", "csv"]), default="auto", show_default=True,
              help="Trajectory file format (auto: .csv -> csv, 12 numbers per line -> kitti, else tum).")
@click.option("--csv-columns", default=None, help="CSV column names, e.g. 't=time,x=east,y=north,z=up,qx=qx,qy=qy,"
              "qz=qz,qw=qw' (defaults: t x y z qx qy qz qw; no quaternion columns: positions only).")
@click.option("--fps", type=POSITIVE, default=None, help="KITTI files: timestamps are line index / fps.")
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="PNG: top-down trajectories and dX dY dZ d-yaw over time with the gaps shaded.")
@json_option
@quiet_option
def traj(estimate, reference, align, t_max_diff, t_offset, delta, delta_m, yaw_offset, fmt, csv_columns, fps,
         plot, as_json, quiet):
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
    """
    from mst.eval.traj import TrajConfig, evaluate_trajectories, report_rows, uav_rows

    check_outputs([plot], [estimate, reference])
    cfg = TrajConfig(align=align, t_max_diff=t_max_diff, t_offset=t_offset, delta=delta, delta_m=delta_m,
                     yaw_offset_deg=yaw_offset, fmt=fmt, csv_columns=csv_columns, fps=fps)
    s = evaluate_trajectories(estimate, reference, cfg)
    series = s.pop("series")
    for note in s["notes"]:
        info(f"note: {note}", quiet)
    if plot is not None:
        from mst.eval.plots import trajectory_figure

        gaps = [(g["t_start"], g["t_end"]) for g in s["gaps"]["ranges"]]
        with atomic_output(plot) as tmp:
            trajectory_figure(tmp, series["t_ref_all"], series["xyz_ref_all"], series["t"], series["xyz_est"],
                              series["dxyz"], series["dyaw"], gaps,
                              title=f"{Path(estimate).name} vs {Path(reference).name} (align {align})")
    if not quiet:
        print_table("trajectory errors", ["metric", "value"],
                    [[a.replace("[", "\\["), b] for a, b in report_rows(s)])
        print_table("UAV table (estimate - reference)", ["", "mean", "std"],
                    [[a.replace("[", "\\["), b, c] for a, b, c in uav_rows(s)])
        if s["gaps"]["count"]:
            info("gaps: " + ", ".join(f"frames {g['first']}-{g['last']} ({g['t_start']:.3f}-{g['t_end']:.3f} s)"
                                      for g in s["gaps"]["ranges"][:20])
                 + (" ..." if s["gaps"]["count"] > 20 else ""))
    if as_json:
        emit_json(s)
