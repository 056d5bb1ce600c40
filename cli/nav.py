"""``mst nav``: navigation logs (GPS + AHRS): simulate one from ground truth, fuse one with a vision track."""

from __future__ import annotations

import click

from mst.cli.common import emit_json, info, json_option, quiet_option


@click.group("nav")
def nav_group() -> None:
    """Navigation logs (GPS + AHRS): simulate, fuse with the vision trajectory.

    \b
    Examples:
      mst nav simulate --gt seq/gt.txt -o seq/nav.csv --seed 1
      mst nav fuse --traj traj.txt --nav seq/nav.csv -o fused.txt --json
    """


def _sim_options(f):
    opts = [
        click.option("--seed", type=int, default=0, show_default=True, help="Seed of the errors."),
        click.option("--rate", "rate_hz", type=float, default=5.0, show_default=True, help="Rows per second (GPS and AHRS)."),
        click.option("--gps-sigma", nargs=2, type=float, default=(3.0, 5.0), show_default=True, metavar="H V",
                     help="GPS white noise, metres (horizontal per axis, vertical)."),
        click.option("--gps-bias-rw", type=float, default=0.05, show_default=True, help="GPS bias random walk, m/sqrt(s)."),
        click.option("--outlier-rate", type=float, default=0.02, show_default=True, help="Share of fixes hit by multipath (15-40 m)."),
        click.option("--dropouts", type=int, default=1, show_default=True, help="GPS dropouts of 5-10 s (fix = 0)."),
        click.option("--ahrs-sigma", type=float, default=3.0, show_default=True, help="AHRS white noise, deg."),
        click.option("--ahrs-yaw-bias", type=float, default=2.0, show_default=True, help="Constant AHRS heading bias, deg."),
        click.option("--mount", nargs=3, type=float, default=(60.0, -20.0, 0.0), show_default=True, metavar="YAW PITCH ROLL",
                     help="Camera mount relative to the platform, deg."),
        click.option("--lever", nargs=3, type=float, default=(0.10, 0.0, -0.15), show_default=True, metavar="DX DY DZ",
                     help="Camera position in the body frame (x fwd, y left, z up), m."),
        click.option("--world-yaw", type=float, default=0.0, show_default=True, help="Model-to-world rotation about up, deg."),
        click.option("--world-offset", nargs=3, type=float, default=(0.0, 0.0, 0.0), show_default=True, metavar="X Y Z",
                     help="Model-to-world translation, m."),
        click.option("--enh-offset", nargs=3, type=float, default=None, metavar="E N H",
                     help="Write easting,northing,height columns with this offset (a '# offset:' line)."),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


def _sim_config(o: dict):
    from mst.pipeline.navlog import NavSimConfig

    return NavSimConfig(rate_hz=o["rate_hz"], sigma_h_m=o["gps_sigma"][0], sigma_v_m=o["gps_sigma"][1],
                        bias_rw_m_per_sqrt_s=o["gps_bias_rw"], outlier_rate=o["outlier_rate"], dropouts=o["dropouts"],
                        ahrs_sigma_deg=o["ahrs_sigma"], ahrs_yaw_bias_deg=o["ahrs_yaw_bias"], mount_ypr_deg=tuple(o["mount"]),
                        lever_arm_m=tuple(o["lever"]), world_yaw_deg=o["world_yaw"], world_offset_m=tuple(o["world_offset"]),
                        enh_offset=tuple(o["enh_offset"]) if o["enh_offset"] else None, seed=o["seed"])


def simulate_nav_files(gt_path, out_path, cfg) -> dict:
    """Read a TUM ground truth, simulate, write ``out_path`` and ``<stem>.truth.json`` atomically."""
    from pathlib import Path

    from mst import atomic_outputs
    from mst.core.trajectory import read_tum
    from mst.pipeline.navlog import simulate_nav, write_sim_outputs

    t, T = read_tum(gt_path)
    res = simulate_nav(t, T, cfg)
    out = Path(out_path)
    truth = out.with_name(out.stem + ".truth.json")
    with atomic_outputs(out, truth) as (tmp, tmp_truth):
        write_sim_outputs(res, tmp, tmp_truth)
    return {"nav": str(out), "truth": str(truth), **res.to_json()}


@nav_group.command("simulate")
@click.option("--gt", "gt_path", required=True, type=click.Path(dir_okay=False), help="Ground truth (TUM, e.g. mst synth's gt.txt).")
@click.option("-o", "--output", "out", required=True, type=click.Path(dir_okay=False), help="nav.csv to write (+ <stem>.truth.json).")
@_sim_options
@json_option
@quiet_option
def simulate(gt_path, out, as_json, quiet, **opts):
    """Simulate a GPS/AHRS log (nav.csv) from a ground-truth camera trajectory.

    GPS: antenna position + white noise + random-walk bias + multipath outliers + dropouts;
    AHRS: yaw/pitch/roll + white noise + a heading bias; a camera mount and lever arm; seeded.
    The truth (model-to-world, mount, biases) goes to <stem>.truth.json.

    \b
    Examples:
      mst nav simulate --gt seq/gt.txt -o seq/nav.csv --seed 1
      mst nav simulate --gt gt.txt -o nav.csv --world-yaw 30 --enh-offset 389000 5820000 40
    """
    s = simulate_nav_files(gt_path, out, _sim_config(opts))
    info(f"{s['rows']} rows ({s['fixes']} fixes, {s['outliers']} multipath) -> {out}", quiet)
    if as_json:
        emit_json(s)


@nav_group.command("fuse")
@click.option("--traj", "traj_path", required=True, type=click.Path(dir_okay=False),
              help="Vision trajectory (TUM, mst track); <stem>.cov.csv and <stem>.csv beside it are used when present.")
@click.option("--nav", "nav_path", required=True, type=click.Path(dir_okay=False), help="Navigation log (nav.csv).")
@click.option("-o", "--output", "out", required=True, type=click.Path(dir_okay=False),
              help="Fused trajectory (TUM, every frame); <stem>.cov.csv beside it (+ <stem>.json with --json).")
@click.option("--cov", "cov_path", type=click.Path(dir_okay=False), default=None, help="Vision covariance side file [TRAJ stem.cov.csv].")
@click.option("--mode", type=click.Choice(["smoother", "filter"]), default="smoother", show_default=True,
              help="smoother: offline (RTS); filter: causal Kalman filter estimates.")
@click.option("--offset", nargs=3, type=float, default=None, metavar="E N H", help="Subtracted from easting,northing,height [the log's '# offset:'].")
@click.option("--lever", nargs=3, type=float, default=(0.0, 0.0, 0.0), show_default=True, metavar="DX DY DZ",
              help="Camera position in the body frame, m (not estimated).")
@click.option("--mount-rotation", "mount_path", type=click.Path(dir_okay=False), default=None,
              help="Fixed R_body_cam (3x3 or quaternion file) instead of estimating the mount.")
@click.option("--model-to-world", "m2w_path", type=click.Path(dir_okay=False), default=None,
              help="Fixed 4x4 T_world_model instead of estimating it (e.g. a georeferenced model: identity).")
@click.option("--gps-sigma", nargs=2, type=float, default=(3.0, 5.0), show_default=True, metavar="H V", help="GPS noise, m.")
@click.option("--ahrs-sigma", type=float, default=3.0, show_default=True, help="AHRS noise, deg.")
@click.option("--vision-sigma", nargs=2, type=float, default=(0.05, 0.3), show_default=True, metavar="M DEG",
              help="Vision noise when no covariance file is given (x3 for SLAM frames).")
@click.option("--accel-sigma", type=float, default=1.0, show_default=True, help="Motion model: white acceleration, m/s^2/sqrt(Hz).")
@click.option("--ang-accel-sigma", type=float, default=2.0, show_default=True, help="Motion model: white angular acceleration, deg/s^2/sqrt(Hz).")
@json_option
@quiet_option
def fuse(traj_path, nav_path, out, cov_path, mode, offset, lever, mount_path, m2w_path, gps_sigma, ahrs_sigma,
         vision_sigma, accel_sigma, ang_accel_sigma, as_json, quiet):
    """Fuse a vision trajectory with a GPS/AHRS log (robust Kalman smoother, calibration estimated).

    Estimates the model-to-world transform (yaw + translation), the camera mount rotation
    (absorbing a constant AHRS heading bias) and the GPS bias (random walk); Huber-robust to GPS
    multipath. Vision gaps (lost frames) are bridged by GPS/AHRS, GPS dropouts by vision.

    \b
    Outputs: OUT (TUM, camera pose in the model frame, every frame of the video's time range),
    <stem>.cov.csv (t, source vision|nav, 6x6 covariance: x y z m, rx ry rz rad model-frame
    perturbation), <stem>.json with --json (calibration, outlier counts; also on stdout).

    \b
    Examples:
      mst nav fuse --traj traj.txt --nav nav.csv -o fused.txt --json
      mst nav fuse --traj traj.txt --nav nav.csv -o causal.txt --mode filter --lever 0.1 0 -0.15
    """
    import json
    from pathlib import Path

    import numpy as np

    from mst import InputError, atomic_outputs
    from mst.core.poses import read_rigid_transform
    from mst.core.trajectory import format_tum, read_tum
    from mst.pipeline.navfusion import (
        FusionConfig,
        cov_path_for,
        format_cov_csv,
        fuse_navigation,
        read_cov_csv,
    )
    from mst.pipeline.navlog import read_mount_rotation, read_navlog

    t_v, T_v = read_tum(traj_path)
    nav = read_navlog(nav_path, offset=offset)
    cov = None
    cp = Path(cov_path) if cov_path else cov_path_for(traj_path)
    if cov_path or cp.is_file():
        t_c, C = read_cov_csv(cp)
        m = {round(x, 6): i for i, x in enumerate(t_c)}
        idx = [m.get(round(x, 6)) for x in t_v]
        if any(i is None for i in idx):
            raise InputError(cp, f"{sum(i is None for i in idx)} trajectory poses have no covariance row (times differ)")
        cov = C[idx]
    cfg = FusionConfig(mode=mode, gps_sigma_h_m=gps_sigma[0], gps_sigma_v_m=gps_sigma[1], ahrs_sigma_deg=ahrs_sigma,
                       vision_sigma_m=vision_sigma[0], vision_sigma_deg=vision_sigma[1], accel_sigma_mps2=accel_sigma,
                       ang_accel_sigma_dps2=ang_accel_sigma, lever_arm_m=tuple(lever),
                       R_body_cam=read_mount_rotation(mount_path) if mount_path else None,
                       T_world_model=read_rigid_transform(m2w_path, "model-to-world file") if m2w_path else None)
    if cov is None:
        s2 = np.array([cfg.vision_sigma_m**2] * 3 + [np.radians(cfg.vision_sigma_deg) ** 2] * 3)
        cov = np.tile(np.diag(s2), (len(t_v), 1, 1))
        status_csv = Path(traj_path).with_suffix(".csv")
        if status_csv.is_file():  # mst track's per-frame status: SLAM-only frames are less certain
            import csv

            with open(status_csv, newline="") as f:
                try:
                    st = {round(float(r["time"]), 6): r.get("status") for r in csv.DictReader(f) if r.get("time")}
                except (ValueError, KeyError):
                    st = {}  # not mst track's per-frame CSV: no statuses
            slam = np.array([st.get(round(x, 6)) == "slam" for x in t_v])
            cov[slam] *= 9.0
    res = fuse_navigation(t_v, T_v, cov, nav, cfg, nav_name=nav_path)
    out = Path(out)
    cov_out = cov_path_for(out)
    json_out = out.with_suffix(".json") if as_json else None
    summary = {"traj": str(out), "cov": str(cov_out), "vision": str(traj_path), "nav": str(nav_path), **res.to_json()}
    with atomic_outputs(out, cov_out, json_out) as (tmp, tmp_cov, tmp_json):
        tmp.write_text(f"# mst nav fuse ({mode}): TUM camera pose in the model frame, every frame; covariance in {cov_out.name}\n"
                       + format_tum(res.t, res.T_model_cam))
        tmp_cov.write_text(format_cov_csv(res.t, res.cov, np.where(res.has_vision, "vision", "nav")))
        if tmp_json is not None:
            tmp_json.write_text(json.dumps(summary, indent=2) + "\n")
    c = res.calib
    info(f"fused {len(res.t)} frames ({int(res.has_vision.sum())} with vision, {int((~res.has_vision).sum())} bridged by nav); "
         f"mount yaw/pitch/roll {c['mount_ypr_deg'][0]:.2f} {c['mount_ypr_deg'][1]:.2f} {c['mount_ypr_deg'][2]:.2f} deg, "
         f"model-to-world yaw {c['world_yaw_deg']:.2f} deg (std {c['world_yaw_std_deg']:.2f}), "
         f"{res.stats['gps_outliers']} GPS outliers -> {out}", quiet)
    if as_json:
        emit_json(summary)
