"""``mst c2m``: cloud-to-mesh distance statistics (Table 1 of the RGB-D paper)."""

from __future__ import annotations

import os
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

# numpy is imported later, inside the command: OpenBLAS then starts no thread pool. mst c2m makes no
# BLAS call worth a thread (its numpy work is elementwise, the searches are compiled kernels), while
# the pool's threads, started at numpy's import, spin on the other core: 100 ms of the 810k-point UTM
# bench case's 450 ms CPU (perf stat task-clock, median of 5), against the kernels' own two threads
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _keep_freed_memory() -> None:
    """glibc: serve arrays up to 32 MiB from the heap and keep freed memory for reuse (mallopt
    M_MMAP_THRESHOLD, M_TRIM_THRESHOLD). By default each large array of the pass (chunk, shifted
    points, search results, ...) is a fresh mmap whose pages fault in one by one; reused heap memory
    does not: 29.4k -> 23.5k page faults and 30-40 ms less CPU on the 810k-point UTM bench case
    (perf stat, median of 5). Other C libraries: nothing is changed."""
    import ctypes
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL("libc.so.6")
        libc.mallopt(-3, 32 << 20)   # M_MMAP_THRESHOLD (glibc's maximum for it)
        libc.mallopt(-1, 1 << 30)    # M_TRIM_THRESHOLD: freed heap memory stays mapped (reused)
    except (OSError, AttributeError):
        pass


def _no_final_collection() -> None:
    """At interpreter exit, freeze the objects left (gc.freeze, from an atexit handler: it runs before
    the final collection): the process ends, nothing needs collecting, and the final collection's walk
    over every object of numpy, click and mst took 25-35 ms CPU of the 810k-point UTM bench case
    (perf stat task-clock, medians of 5, 300-340 ms). In-process callers are unaffected until their exit."""
    import atexit
    import gc

    if not getattr(_no_final_collection, "done", False):
        atexit.register(gc.freeze)
        _no_final_collection.done = True


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
@click.argument("clouds", nargs=-1, required=True, metavar="CLOUD...")
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
@click.option("--workers", type=click.IntRange(1), default=None,
              help="Distribute the chunks on a local dask cluster of this many worker processes (one thread each).")
@click.option("--scheduler", default=None, metavar="ADDRESS",
              help="Distribute the chunks on an existing dask cluster (tcp://host:8786).")
@click.option("--chunks-per-task", type=click.IntRange(1), default=None,
              help="With --workers/--scheduler: chunks of a LAS/LAZ/binary PLY file per dask task  [default: 2].")
@click.option("--exact-median", is_flag=True, default=None,
              help="With --workers/--scheduler: a second pass for the exact median (default: from the merged "
              "histogram, within median_bound_m).")
@click.option("--output-dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="With --workers/--scheduler: write each cloud (one task per file) to DIR/<stem>_c2m.<las|laz> "
              "with the extra dimension C2M_absolute_distances, or DIR/<stem>_c2m.ply with the scalar field.")
@config_options()
@json_option
@quiet_option
@verbosity_options
def c2m(clouds, mesh, thresholds, signed, max_dist, output, as_csv, markdown, plot, chunk, engine, workers,
        scheduler, chunks_per_task, exact_median, output_dir, config_file, set_values, as_json, quiet, verbose):
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
      mst c2m big.laz building.obj --workers 2 --json          # chunks on a local dask cluster
      mst c2m 'survey/*.laz' tin.ply --scheduler tcp://10.0.0.5:8786 --output-dir c2m/

    \b
    Distributed (--workers N or --scheduler ADDRESS; CLOUD may then be many files, folders of
    .las/.laz/.ply or globs): LAS/LAZ and binary PLY are cut into tasks of --chunks-per-task chunks
    (other formats one task per file); each worker builds the mesh index once; only per-chunk sums
    come back. Count, mean, std, RMS, min, max and Table 1 are bit-identical to the single-process
    run; the median comes from a merged 65536-bin histogram (within median_bound_m in --json) or is
    exact with --exact-median. Unsigned distances, grid engine; no -o/--plot (use --output-dir).

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
    if workers is not None or scheduler is not None:
        for opt, val in (("-o", output), ("--plot", plot)):
            if val is not None:
                raise click.UsageError(f"{opt} needs the distances in one process; with --workers/--scheduler use "
                                       "--output-dir (one distance cloud per file) and --json/--markdown/--csv")
        run_distributed(mesh, clouds, cfg, workers=workers, scheduler=scheduler, chunks_per_task=chunks_per_task or 2,
                        exact_median=bool(exact_median), output_dir=output_dir, markdown=markdown, as_csv=as_csv,
                        as_json=as_json, quiet=quiet)
        return
    for opt, val in (("--chunks-per-task", chunks_per_task), ("--exact-median", exact_median),
                     ("--output-dir", output_dir)):
        if val is not None:
            raise click.UsageError(f"{opt} is an option of a distributed run: add --workers N or --scheduler ADDRESS")
    if len(clouds) > 1:
        raise click.UsageError(f"{len(clouds)} clouds given: many tiles run distributed (--workers N or "
                               "--scheduler ADDRESS), one process takes one CLOUD")
    cloud = Path(clouds[0])
    if cloud.is_dir():
        raise click.BadParameter(f"'{cloud}' is a folder (tiles in a folder: add --workers N or --scheduler "
                                 "ADDRESS)", param_hint="'CLOUD'")
    check_outputs([output, markdown, plot], [cloud, mesh])
    if output is not None and output.suffix.lower() != ".ply":
        raise InputError(output, "-o must be a .ply file")
    total = open_cloud(cloud).count
    _keep_freed_memory()
    _no_final_collection()
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


def _clouds(specs) -> list[str]:
    """Files, folders (their .las/.laz/.ply) and globs, in the given order (each sorted)."""
    import glob

    out: list[str] = []
    for spec in specs:
        p = Path(spec)
        if p.is_dir():
            out += sorted(str(f) for f in p.iterdir() if f.suffix.lower() in (".las", ".laz", ".ply"))
        elif any(c in str(spec) for c in "*?["):
            out += sorted(glob.glob(str(spec)))
        elif p.is_file():
            out.append(str(spec))
        else:
            raise InputError(p, "cloud file does not exist")
    if not out:
        raise InputError(specs[0], "no cloud files found")
    return out


def run_distributed(mesh, clouds, cfg, *, workers: int | None, scheduler: str | None, chunks_per_task: int,
                    exact_median: bool, output_dir: Path | None, markdown: Path | None = None, as_csv: bool = False,
                    as_json: bool = False, quiet: bool = False) -> None:
    """``mst c2m --workers/--scheduler`` (and ``mst c2m-tiles``): the clouds' chunks on dask, reduced by
    :func:`mst.eval.c2m.tiles.c2m_tiles`; the same tables, Markdown, CSV and --json as a single run."""
    from mst.eval.batch.config import BatchConfig
    from mst.eval.batch.runner import close_client, connect
    from mst.eval.c2m import markdown_report, overall_rows, table1_csv, table1_rows
    from mst.eval.c2m.tiles import c2m_tiles, output_name

    files = _clouds(clouds)
    mesh = Path(mesh)
    if not mesh.is_file():
        raise InputError(mesh, "mesh file does not exist")
    outs = []
    if output_dir is not None:
        if not output_dir.is_dir():
            raise InputError(output_dir, "output folder does not exist")
        outs = [output_name(f, output_dir) for f in files]
    check_outputs([*outs, markdown], [mesh, *files])
    n_workers = workers or 2
    client = connect(BatchConfig(workers=n_workers, scheduler=scheduler))  # an unreachable address: one line
    try:
        res = c2m_tiles(files, mesh, cfg, client=client, chunks_per_task=chunks_per_task, out_dir=output_dir,
                        exact_median=exact_median)
    finally:
        close_client(client)
    summary = res.to_json()
    summary["scheduler"] = scheduler or f"LocalCluster({n_workers})"
    summary["dask"] = {"workers": None if scheduler else n_workers, "scheduler": scheduler,
                       "chunks_per_task": chunks_per_task, "exact_median": exact_median}
    if markdown is not None:
        with atomic_output(markdown) as tmp:
            Path(tmp).write_text(markdown_report(summary))
    if not quiet:
        rows = [[c.replace("[", "\\[") for c in r] for r in table1_rows(summary)]
        print_table(f"C2M: {summary['points_valid']:,} points in {len(files)} file(s) vs {res.mesh_triangles:,} "
                    f"triangles, {res.tasks} tasks on {summary['scheduler']}", rows[0], rows[1:])
        print_table("overall", ["statistic", "unsigned"],
                    [[c.replace("[", "\\[") for c in r] for r in overall_rows(summary)])
        med = ("beyond the histogram" if summary["unsigned"]["median"] is None
               else f"median {res.median_method}" + (f", within ±{res.median_bound_m:.1e} m" if res.median_bound_m else ""))
        info(f"{med}; {res.elapsed_s:.2f} s")
    if as_json:
        emit_json(summary)
    elif as_csv:
        click.echo(table1_csv(summary), nl=False)
