"""``mst report``: one self-contained HTML page of a run folder or a batch folder."""

from __future__ import annotations

from pathlib import Path

import click

from mst import atomic_output, check_outputs
from mst.cli.common import (
    CONFIG_CLASSES,
    POSITIVE,
    build_config,
    config_options,
    emit_json,
    info,
    json_option,
    quiet_option,
    setup_logging,
    verbosity_options,
)

CONFIG_CLASSES["mst report"] = "mst.eval.report.config:ReportConfig"


@click.command("report")
@click.argument("run_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("-o", "--output", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="The HTML file to write (self-contained: images inlined, no network needed).")
@click.option("--frames", default=None, help="The run's frames (video or image folder), for the overlay strip "
                                             "[a batch run: from its track command].")
@click.option("--model", type=click.Path(dir_okay=False), default=None, help="The tracked model, for the overlays.")
@click.option("--camera", type=click.Path(dir_okay=False), default=None, help="The camera file, for the overlays.")
@click.option("--fps", type=POSITIVE, default=None, help="The --fps the run was tracked with.")
@click.option("--overlay-frames", type=int, default=None, help="Frames in the overlay strip [default: 6].")
@config_options()
@json_option
@quiet_option
@verbosity_options
def report(run_dir, output, frames, model, camera, fps, overlay_frames, config_file, set_values, as_json, quiet,
           verbose):
    """Write one HTML report of RUN_DIR: a run folder (e.g. the demo's) or a batch folder (mst batch -o).

    \b
    Sections: Table 1 (c2m.json), the C2M histogram and a colour-mapped top/side view of the cloud,
    the trajectory against the ground truth (dX dY dZ d-yaw table, ATE/RPE, figure; eval.json), the
    per-frame status timeline (traj.csv), a strip of overlay frames (the model drawn at the tracked
    pose), and the commands and configurations that produced the run. Images are inlined PNGs; the
    page needs no network and no script.

    \b
    Examples:
      mst report demo-out -o demo-out/report.html --frames demo-out/seq/rgb --model demo-out/building.wrl \\
                 --camera demo-out/seq/camera.json --fps 30
      mst report runs/ -o runs/report.html        # a batch: overview + one section per sequence
    """
    setup_logging(quiet, verbose, "mst report")
    from mst.eval.report.build import build_report
    from mst.eval.report.config import ReportConfig

    cfg = build_config(ReportConfig, config_file=config_file, set_values=set_values, section_name="report",
                       options={"overlay_frames": overlay_frames}, flags={"overlay_frames": "--overlay-frames"})
    check_outputs([output], [])
    rep = build_report(run_dir, cfg, frames=frames, model=model, camera=camera, fps=fps)
    with atomic_output(output) as tmp:
        tmp.write_text(rep.html, encoding="utf-8")
    info(f"{output}: {len(rep.sections)} sections, {rep.images} images, {len(rep.html.encode()) / 1e6:.1f} MB"
         + (f"; {len(rep.notes)} parts not drawn (see the page)" if rep.notes else ""), quiet)
    if as_json:
        emit_json({"output": str(output), **rep.to_json()})
