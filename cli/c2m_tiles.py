"""``mst c2m-tiles``: cloud-to-mesh statistics of many cloud tiles (or one large LAS/LAZ) on dask."""

from __future__ import annotations

import glob
from pathlib import Path

import click

from mst import InputError
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

CONFIG_CLASSES["mst c2m-tiles"] = "mst.eval.c2m.config:C2MConfig"  # for --show-config
FLAGS = {"thresholds_m": "--thresholds", "max_dist_m": "--max-dist", "chunk_points": "--chunk"}


def _clouds(specs: tuple[str, ...]) -> list[str]:
    """Files, folders (their .las/.laz/.ply) and globs, in the given order (each sorted)."""
    out: list[str] = []
    for s in specs:
        p = Path(s)
        if p.is_dir():
            out += sorted(str(f) for f in p.iterdir() if f.suffix.lower() in (".las", ".laz", ".ply"))
        elif any(c in s for c in "*?["):
            out += sorted(glob.glob(s))
        elif p.is_file():
            out.append(s)
        else:
            raise InputError(p, "cloud file does not exist")
    if not out:
        raise InputError(specs[0], "no cloud files found")
    return out


@click.command("c2m-tiles")
@click.argument("mesh", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("clouds", nargs=-1, required=True)
@click.option("--thresholds", default=None, help="Max. C2M distances [m] of the Table-1 columns, comma separated "
                                                 "[default: 0.1,0.2,0.5,1.0].")
@click.option("--max-dist", type=float, default=None, help="Points farther than this [m] are counted as beyond it.")
@click.option("--chunk", type=int, default=None, help="Points per chunk [default: 1000000].")
@click.option("--chunks-per-task", type=click.IntRange(1), default=4, show_default=True,
              help="Chunks of a LAS/LAZ file per dask task.")
@click.option("--workers", type=click.IntRange(1), default=2, show_default=True, help="Local worker processes.")
@click.option("--scheduler", default=None, metavar="ADDRESS", help="An existing dask cluster (tcp://host:8786).")
@click.option("--exact-median", is_flag=True, help="A second pass over the points for the exact median "
                                                  "(default: from the histogram, within median_bound_m).")
@click.option("--output-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Write each LAS/LAZ tile with the distance as the extra dimension C2M_absolute_distances "
                   "to DIR/<stem>_c2m.<las|laz> (one task per tile).")
@config_options()
@json_option
@quiet_option
@verbosity_options
def c2m_tiles(mesh, clouds, thresholds, max_dist, chunk, chunks_per_task, workers, scheduler, exact_median, output_dir,
              config_file, set_values, as_json, quiet, verbose):
    """Table 1 and the overall C2M statistics of the cloud tiles CLOUDS against MESH, on dask.

    \b
    CLOUDS: files, folders (their .las .laz .ply) or globs; LAS/LAZ are read by point ranges (a task
    per --chunks-per-task chunks), other formats one task per file. The mesh and its index are built
    once per worker; the points are never gathered. Count, mean, std, RMS, min, max and Table 1 are
    bit-identical to `mst c2m` on the same points in the same chunks; the median comes from a merged
    65536-bin histogram (within median_bound_m, in --json), or exact with --exact-median (a second
    pass). Unsigned distances, grid engine.

    \b
    Examples:
      mst c2m-tiles building.obj tiles/ --workers 2 --json
      mst c2m-tiles tin.ply 'survey/*.laz' --scheduler tcp://10.0.0.5:8786 --max-dist 2
      mst c2m-tiles building.obj tiles/ --output-dir c2m/     # + tiles with the distance dimension
    """
    setup_logging(quiet, verbose, prog="mst c2m-tiles")
    from mst import check_outputs
    from mst.eval.batch.config import BatchConfig
    from mst.eval.batch.runner import close_client, connect
    from mst.eval.c2m import C2MConfig, table1_rows
    from mst.eval.c2m.tiles import c2m_tiles as run
    from mst.eval.c2m.tiles import output_name

    thr = None if thresholds is None else [v for v in thresholds.replace(";", ",").split(",") if v.strip()]
    cfg = build_config(C2MConfig, config_file=config_file, set_values=set_values, section_name="c2m", flags=FLAGS,
                       options={"thresholds_m": thr, "max_dist_m": max_dist, "chunk_points": chunk})
    files = _clouds(clouds)
    if not mesh.is_file():
        raise InputError(mesh, "mesh file does not exist")
    if output_dir is not None:
        if not output_dir.is_dir():
            raise InputError(output_dir, "output folder does not exist")
        check_outputs([output_name(f, output_dir) for f in files], [mesh, *files])
    client = connect(BatchConfig(workers=workers, scheduler=scheduler))
    try:
        res = run(files, mesh, cfg, client=client, chunks_per_task=chunks_per_task, out_dir=output_dir,
                  exact_median=exact_median)
    finally:
        close_client(client)
    summary = res.to_json()
    summary["scheduler"] = scheduler or f"LocalCluster({workers})"
    if not quiet:
        rows = [[c.replace("[", "\\[") for c in r] for r in table1_rows(summary)]
        print_table(f"C2M: {summary['points_valid']:,} points in {len(files)} file(s), {res.tasks} tasks",
                    rows[0], rows[1:])
        u = summary["unsigned"]
        med = "beyond the histogram" if u["median"] is None else f"{u['median']:.6f} m (±{res.median_bound_m:.1e})"
        info(f"count {u['count']:,}, mean {u['mean']:.6f} m, median {med}, std {u['std']:.6f} m, "
             f"rms {u['rms']:.6f} m, max {u['max']:.6f} m; {res.elapsed_s:.2f} s")
    if as_json:
        emit_json(summary)
