"""``mst c2m-tiles MESH CLOUD...``: the alias of ``mst c2m CLOUD... MESH --workers N`` (one engine,
:func:`mst.cli.c2m.run_distributed`; the mesh first, as in the first tiled release)."""

from __future__ import annotations

from pathlib import Path

import click

from mst.cli.common import (
    CONFIG_CLASSES,
    build_config,
    config_options,
    json_option,
    quiet_option,
    setup_logging,
    verbosity_options,
)

CONFIG_CLASSES["mst c2m-tiles"] = "mst.eval.c2m.config:C2MConfig"  # for --show-config
FLAGS = {"thresholds_m": "--thresholds", "max_dist_m": "--max-dist", "chunk_points": "--chunk"}


@click.command("c2m-tiles")
@click.argument("mesh", type=click.Path(dir_okay=False, path_type=Path))
@click.argument("clouds", nargs=-1, required=True)
@click.option("--thresholds", default=None, help="Max. C2M distances [m] of the Table-1 columns, comma separated "
                                                 "[default: 0.1,0.2,0.5,1.0].")
@click.option("--max-dist", type=float, default=None, help="Points farther than this [m] are counted as beyond it.")
@click.option("--chunk", type=int, default=None, help="Points per chunk [default: 1000000].")
@click.option("--chunks-per-task", type=click.IntRange(1), default=2, show_default=True,
              help="Chunks of a LAS/LAZ/binary PLY file per dask task.")
@click.option("--workers", type=click.IntRange(1), default=2, show_default=True, help="Local worker processes.")
@click.option("--scheduler", default=None, metavar="ADDRESS", help="An existing dask cluster (tcp://host:8786).")
@click.option("--exact-median", is_flag=True, help="A second pass over the points for the exact median "
                                                  "(default: from the histogram, within median_bound_m).")
@click.option("--output-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Write each tile with the distance to DIR/<stem>_c2m.<las|laz|ply> (one task per tile).")
@config_options()
@json_option
@quiet_option
@verbosity_options
def c2m_tiles(mesh, clouds, thresholds, max_dist, chunk, chunks_per_task, workers, scheduler, exact_median, output_dir,
              config_file, set_values, as_json, quiet, verbose):
    """Alias of `mst c2m CLOUDS... MESH --workers N` (mesh first): Table 1 and the overall C2M statistics
    of the cloud tiles CLOUDS against MESH, on dask.

    \b
    CLOUDS: files, folders (their .las .laz .ply) or globs. See `mst c2m --help` (distributed).

    \b
    Examples:
      mst c2m-tiles building.obj tiles/ --workers 2 --json
      mst c2m-tiles tin.ply 'survey/*.laz' --scheduler tcp://10.0.0.5:8786 --max-dist 2
      mst c2m-tiles building.obj tiles/ --output-dir c2m/     # + tiles with the distance dimension
    """
    setup_logging(quiet, verbose, prog="mst c2m-tiles")
    from mst.cli.c2m import run_distributed
    from mst.eval.c2m import C2MConfig

    thr = None if thresholds is None else [v for v in thresholds.replace(";", ",").split(",") if v.strip()]
    cfg = build_config(C2MConfig, config_file=config_file, set_values=set_values, section_name="c2m", flags=FLAGS,
                       options={"thresholds_m": thr, "max_dist_m": max_dist, "chunk_points": chunk})
    run_distributed(mesh, clouds, cfg, workers=workers, scheduler=scheduler, chunks_per_task=chunks_per_task,
                    exact_median=exact_median, output_dir=output_dir, as_json=as_json, quiet=quiet)
