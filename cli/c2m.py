"""``mst c2m``: cloud-to-mesh distance statistics (Table 1 of the RGB-D paper)."""

from __future__ import annotations

from pathlib import Path

import click

from mst import InputError, atomic_output, check_outputs
from mst.cli.common import (
    CONFIG_CLASSES,
    build_config,
    config_options,
    emit_json,
    info,
    json_option,
    print_table,
    progress_bar,
    quiet_option,
    setup_logging,
    verbosity_options,
)

CONFIG_CLASSES["mst c2m"] = "mst.eval.c2m.config:C2MConfig"  # for --show-config

#: config field -> the option that sets it (errors on these fields name the option)
FLAGS = {"thresholds_m": "--thresholds", "signed": "--signed", "max_dist_m": "--max-dist",
         "chunk_points": "--chunk", "engine": "--engine"}


def _floats(ctx, param, value: str | None) -> tuple[float, ...] | None:
    """Comma-separated numbers (their bounds are C2MConfig's)."""
    if value is None:
        return None
    try:
        return tuple(float(v) for v in value.replace(";", ",").split(",") if v.strip())
    except ValueError:
        raise click.BadParameter(f"{value!r}: expected comma-separated numbers, e.g. 0.1,0.2,0.5,1") from None


@click.command("c2m")
@click.argument("cloud", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("mesh", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--thresholds", default=None, callback=_floats,
              help="Max. C2M distances [m] of the Table-1 columns, comma separated  [default: 0.1,0.2,0.5,1.0].")
@click.option("--signed", is_flag=True, default=None, help="Also signed distances: + on the side the faces point to (outside), "
              "- inside; angle-weighted pseudo-normal of the nearest face/edge/vertex.")
@click.option("--max-dist", type=float, default=None, help="Points farther than this [m] are counted as "
              "beyond it (NaN in -o) and left out of the overall statistics.")
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the cloud with scalar fields C2M_absolute_distances (and C2M_signed_distances) "
              "as binary PLY (CloudCompare opens them as scalar fields).")
@click.option("--csv", "as_csv", is_flag=True, help="Print Table 1 as CSV on stdout.")
@click.option("--markdown", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write Table 1 and the overall statistics as Markdown to this file.")
@click.option("--plot", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write a PNG histogram of the distances with the thresholds marked.")
@click.option("--chunk", type=int, default=None,
              help="Points per streamed chunk (memory bound, >= 1000)  [default: 1000000].")
@click.option("--engine", default=None, metavar="[auto|bvh|grid]",
              help="Nearest-triangle search: auto/grid = compiled exact float64 grid search for every mesh (dense "
              "candidate lists up to 5000 triangles, binned cells with ring search above); bvh = Open3D BVH + "
              "exact float64 recheck  [default: auto].")
@config_options()
@json_option
@quiet_option
@verbosity_options
def c2m(cloud, mesh, thresholds, signed, max_dist, output, as_csv, markdown, plot, chunk, engine, config_file,
        set_values, as_json, quiet, verbose):
    """Cloud-to-mesh distances of CLOUD to MESH and their statistics.

    Exact point-to-triangle distances (nearest triangle, float64, after a global shift so
    georeferenced coordinates keep their precision). Prints Table 1 (percentage of points under
    each threshold, mean and std of those distances) and overall count / mean / median / std /
    RMS / max. NaN/inf points are counted and excluded (the summary says how many;
    points_nonfinite in --json); a cloud with a coordinate beyond 1e12 m is refused as corrupt.

    \b
    CLOUD: .ply (binary/ascii) .pcd .xyz .txt .csv .las .laz
    MESH:  .obj .ply .stl .off, polygon models .wrl .cao (triangulated on load)

    \b
    Examples:
      mst c2m cloud.ply building.obj
      mst c2m cloud.ply building.obj --json
      mst c2m cloud.laz tin.ply --signed --max-dist 2 -o cloud_c2m.ply --plot hist.png
      mst c2m cloud.ply building.wrl --thresholds 0.05,0.1,0.2 --csv --markdown table1.md
      mst c2m cloud.ply building.obj --config c2m.yaml --set engine=bvh

    Settings (--config FILE, --set KEY=VALUE; the options above override them): thresholds_m,
    signed, max_dist_m, chunk_points, workers, small_mesh_triangles, engine (--show-config lists
    them); the "config" block of --json is the effective set.
    """
    from mst.eval.c2m import C2MConfig, markdown_report, overall_rows, run_c2m, table1_csv, table1_rows
    from mst.eval.cloud_io import open_cloud

    setup_logging(quiet, verbose, prog="mst c2m")
    cfg = build_config(C2MConfig, config_file=config_file, set_values=set_values, section_name="c2m", flags=FLAGS,
                       options={"thresholds_m": thresholds, "signed": signed, "max_dist_m": max_dist,
                                "chunk_points": chunk, "engine": engine})
    check_outputs([output, markdown, plot], [cloud, mesh])
    if output is not None and output.suffix.lower() != ".ply":
        raise InputError(output, "-o must be a .ply file")
    total = open_cloud(cloud).count
    with progress_bar(total, "c2m", quiet=quiet or total < 2_000_000) as advance:
        result = run_c2m(cloud, mesh, cfg, out_cloud=output, progress=advance)
    dist = result.distances
    summary = result.to_json()
    if plot is not None:
        from mst.eval.plots import c2m_histogram

        with atomic_output(plot) as tmp:
            c2m_histogram(tmp, dist, [r["max_dist"] for r in summary["thresholds"]],
                          title=f"C2M {Path(cloud).name} vs {Path(mesh).name}",
                          percents=[r["percent"] for r in summary["thresholds"]])
    if markdown is not None:
        with atomic_output(markdown) as tmp:
            Path(tmp).write_text(markdown_report(summary))
    if not quiet:
        rows = [[c.replace("[", "\\[") for c in r] for r in table1_rows(summary)]  # rich markup escape
        print_table(f"C2M: {summary['points_valid']:,} points vs {summary['mesh_triangles']:,} triangles",
                    rows[0], rows[1:])
        hdr = ["statistic", "unsigned"] + (["signed"] if cfg.signed else [])
        print_table("overall", hdr, [[c.replace("[", "\\[") for c in r] for r in overall_rows(summary)])
        extra = []
        if summary["points_nonfinite"]:
            extra.append(f"{summary['points_nonfinite']:,} NaN/inf points excluded")
        if cfg.max_dist_m is not None:
            extra.append(f"{summary['points_beyond_max_dist']:,} points beyond --max-dist {cfg.max_dist_m:g} m")
        tm = summary["timing"]
        extra.append(f"{tm['total_s']:.2f} s ({tm['points_per_s'] / 1e6:.2f} M points/s in the distance pass)"
                     if tm["points_per_s"] else f"{tm['total_s']:.2f} s")
        info("; ".join(extra))
    if as_json:
        emit_json(summary)
    elif as_csv:
        click.echo(table1_csv(summary), nl=False)
