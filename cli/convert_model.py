"""``mst convert-model``: TIN -> polygon model (.wrl / .cao / .obj)."""

from __future__ import annotations

import sys

import click

from mst.cli.common import (
    CONFIG_CLASSES,
    NON_NEGATIVE,
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

STEPS = ("read", "weld", "orient", "regions", "outlines", "write")
#: config field -> the option that sets it (errors name the flag the user typed)
FLAGS = {"angle_tol_deg": "--angle-tol", "dist_tol_m": "--dist-tol", "weld_tol_m": "--weld-tol"}
CONFIG_CLASSES["mst convert-model"] = "mst.meshtools.convert:ConvertConfig"


@click.command("convert-model")
@click.argument("input_path", metavar="INPUT", type=click.Path(dir_okay=False, path_type=str))
@click.option("-o", "--output", "output_path", required=True, type=click.Path(dir_okay=False, path_type=str),
              help="Polygon model to write; format from the suffix: .wrl (VRML 2.0), .cao (ViSP), .obj.")
@click.option("--angle-tol", type=NON_NEGATIVE, default=None,
              help="Max angle in degrees between any two triangle normals of one polygon "
                   "(each triangle within half of it from the polygon's normal) [default: 1].")
@click.option("--dist-tol", type=NON_NEGATIVE, default=None,
              help="Max distance in metres of a polygon's vertices from its plane "
                   "[default: 1e-4 of the model's bounding-box diagonal].")
@click.option("--weld-tol", type=NON_NEGATIVE, default=None,
              help="Vertices closer than this (metres) are merged first; 0 merges exact duplicates only "
                   "[default: 1e-6].")
@config_options()
@json_option
@quiet_option
@verbosity_options
def convert_model(input_path: str, output_path: str, angle_tol: float | None, dist_tol: float | None,
                  weld_tol: float | None, config_file: str | None, set_values: tuple[str, ...], as_json: bool,
                  quiet: bool, verbose: int) -> None:
    """Group the triangles of a TIN into planar polygons and write a polygon model.

    INPUT is a triangle mesh (.obj .ply .stl .off .wrl .cao or CityJSON). Coplanar,
    edge-connected triangles become one polygon (outer outline plus holes); crease edges stay
    polygon edges; closed parts get outward normals; collinear vertices are removed unless a
    neighbouring polygon needs them (no cracks). Holes are cut open with a bridge edge so that
    VRML and ViSP .cao readers accept them. A summary goes to stderr (and JSON to stdout with
    --json, its "config" block repeats the run with --config). Settings: angle_tol_deg,
    dist_tol_m, weld_tol_m, collinear_tol_m (--config FILE, --set KEY=VALUE; options override).

    \b
    Examples:
      mst convert-model building_tin.obj -o building.wrl
      mst convert-model city.ply -o city.cao --angle-tol 2 --dist-tol 0.02 --json
      mst convert-model city.ply -o city.cao --config convert.yaml --set collinear_tol_m=0.001
    """
    from mst.meshtools.convert import ConvertConfig, summary_lines
    from mst.meshtools.convert import convert_model as run

    setup_logging(quiet, verbose, "mst convert-model")
    cfg = build_config(ConvertConfig, config_file=config_file, set_values=set_values, section_name="convert-model",
                       options={"angle_tol_deg": angle_tol, "dist_tol_m": dist_tol, "weld_tol_m": weld_tol},
                       flags=FLAGS)
    # the bar only on a terminal: in logs and pipes it would leave a stale line before errors
    show_bar = not (quiet or as_json) and sys.stderr.isatty()
    with progress_bar(len(STEPS), "convert-model", quiet=not show_bar) as advance:
        result = run(input_path, output_path, cfg, progress=lambda name: advance())
    for line in summary_lines(result):
        info(line, quiet)
    if as_json:
        emit_json(result.to_json())
