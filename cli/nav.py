"""``mst nav``: navigation logs (GPS + AHRS): simulate one from ground truth, fuse one with a vision track."""

from __future__ import annotations

import click

from mst.cli.common import (
    CONFIG_CLASSES,
    build_config,
    config_options,
    emit_json,
    info,
    json_option,
    quiet_option,
    setup_logging,
    verbosity_options,
)

# for --show-config
CONFIG_CLASSES["mst nav simulate"] = "mst.pipeline.nav.log:NavSimConfig"
CONFIG_CLASSES["mst nav fuse"] = "mst.pipeline.nav.fusion:FusionConfig"


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
        click.option("--seed", type=int, default=None, help="Seed of the errors [default: 0]."),
        click.option("--rate", "rate_hz", type=float, default=None, help="Rows per second (GPS and AHRS) [default: 5]."),
        click.option("--gps-sigma", nargs=2, type=float, default=None, metavar="H V",
                     help="GPS white noise, metres (horizontal per axis, vertical) [default: 3 5]."),
        click.option("--gps-bias-rw", type=float, default=None, help="GPS bias random walk, m/sqrt(s) [default: 0.05]."),
        click.option("--outlier-rate", type=float, default=None,
                     help="Share of fixes hit by multipath (15-40 m) [default: 0.02]."),
        click.option("--dropouts", type=int, default=None, help="GPS dropouts of 5-10 s (fix = 0) [default: 1]."),
        click.option("--ahrs-sigma", type=float, default=None, help="AHRS white noise, deg [default: 3]."),
        click.option("--ahrs-yaw-bias", type=float, default=None, help="Constant AHRS heading bias, deg [default: 2]."),
        click.option("--mount", nargs=3, type=float, default=None, metavar="YAW PITCH ROLL",
                     help="Camera mount relative to the platform, deg [default: 60 -20 0]."),
        click.option("--lever", nargs=3, type=float, default=None, metavar="DX DY DZ",
                     help="Camera position in the body frame (x fwd, y left, z up), m [default: 0.1 0 -0.15]."),
        click.option("--world-yaw", type=float, default=None, help="Model-to-world rotation about up, deg [default: 0]."),
        click.option("--world-offset", nargs=3, type=float, default=None, metavar="X Y Z",
                     help="Model-to-world translation, m [default: 0 0 0]."),
        click.option("--enh-offset", nargs=3, type=float, default=None, metavar="E N H",
                     help="Write easting,northing,height columns with this offset (a '# offset:' line)."),
        click.option("--time-offset", "time_offset_s", type=float, default=None,
                     help="Clock offset of the log: a row measured at video time t is stamped t - OFFSET, s [default: 0]."),
    ]
    for o in reversed(opts):
        f = o(f)
    return f


#: NavSimConfig field -> the option that sets it
SIM_FLAGS = {"seed": "--seed", "rate_hz": "--rate", "sigma_h_m": "--gps-sigma", "sigma_v_m": "--gps-sigma",
             "bias_rw_m_per_sqrt_s": "--gps-bias-rw", "outlier_rate": "--outlier-rate", "dropouts": "--dropouts",
             "ahrs_sigma_deg": "--ahrs-sigma", "ahrs_yaw_bias_deg": "--ahrs-yaw-bias", "mount_ypr_deg": "--mount",
             "lever_arm_m": "--lever", "world_yaw_deg": "--world-yaw", "world_offset_m": "--world-offset",
             "enh_offset_m": "--enh-offset", "time_offset_s": "--time-offset"}


def _pair(v, i):
    return None if v is None else v[i]


def _sim_config(o: dict, config_file=None, set_values=()):
    from mst.pipeline.nav.log import NavSimConfig

    options = {"seed": o["seed"], "rate_hz": o["rate_hz"], "sigma_h_m": _pair(o["gps_sigma"], 0),
               "sigma_v_m": _pair(o["gps_sigma"], 1), "bias_rw_m_per_sqrt_s": o["gps_bias_rw"],
               "outlier_rate": o["outlier_rate"], "dropouts": o["dropouts"], "ahrs_sigma_deg": o["ahrs_sigma"],
               "ahrs_yaw_bias_deg": o["ahrs_yaw_bias"], "mount_ypr_deg": o["mount"], "lever_arm_m": o["lever"],
               "world_yaw_deg": o["world_yaw"], "world_offset_m": o["world_offset"], "enh_offset_m": o["enh_offset"],
               "time_offset_s": o["time_offset_s"]}
    return build_config(NavSimConfig, config_file=config_file, set_values=set_values, section_name="nav_simulate",
                        options=options, flags=SIM_FLAGS)


@nav_group.command("simulate")
@click.option("--gt", "gt_path", required=True, type=click.Path(dir_okay=False), help="Ground truth (TUM, e.g. mst synth's gt.txt).")
@click.option("-o", "--output", "out", required=True, type=click.Path(dir_okay=False), help="nav.csv to write (+ <stem>.truth.json).")
@_sim_options
@config_options()
@json_option
@quiet_option
@verbosity_options
def simulate(gt_path, out, config_file, set_values, as_json, quiet, verbose, **opts):
    """Simulate a GPS/AHRS log (nav.csv) from a ground-truth camera trajectory.

    GPS: antenna position + white noise + random-walk bias + multipath outliers + dropouts;
    AHRS: yaw/pitch/roll + white noise + a heading bias; a camera mount and lever arm; seeded.
    The truth (model-to-world, mount, biases, the error model as "config") goes to <stem>.truth.json.

    \b
    Examples:
      mst nav simulate --gt seq/gt.txt -o seq/nav.csv --seed 1
      mst nav simulate --gt gt.txt -o nav.csv --world-yaw 30 --enh-offset 389000 5820000 40
      mst nav simulate --gt gt.txt -o nav.csv --config errors.yaml --set dropouts=3
    """
    from mst import check_outputs
    from mst.pipeline.nav.run import simulate_nav_files

    setup_logging(quiet, verbose, "mst nav simulate")
    check_outputs([out], [config_file])
    s = simulate_nav_files(gt_path, out, _sim_config(opts, config_file, set_values))
    info(f"{s['rows']} rows ({s['fixes']} fixes, {s['outliers']} multipath) -> {out}", quiet)
    if as_json:
        emit_json(s)


#: FusionConfig field -> the option that sets it
FUSE_FLAGS = {"mode": "--mode", "lever_arm_m": "--lever", "gps_sigma_h_m": "--gps-sigma", "gps_sigma_v_m": "--gps-sigma",
              "ahrs_sigma_deg": "--ahrs-sigma", "vision_sigma_m": "--vision-sigma", "vision_sigma_deg": "--vision-sigma",
              "accel_sigma_mps2": "--accel-sigma", "ang_accel_sigma_dps2": "--ang-accel-sigma",
              "time_offset_s": "--time-offset", "estimate_time_offset": "--estimate-time-offset",
              "estimate_lever_arm": "--estimate-lever-arm"}


@nav_group.command("fuse")
@click.option("--traj", "traj_path", required=True, type=click.Path(dir_okay=False),
              help="Vision trajectory (TUM, mst track); <stem>.cov.csv and <stem>.csv beside it are used when present.")
@click.option("--nav", "nav_path", required=True, type=click.Path(dir_okay=False), help="Navigation log (nav.csv).")
@click.option("-o", "--output", "out", required=True, type=click.Path(dir_okay=False),
              help="Fused trajectory (TUM, every frame); <stem>.cov.csv beside it (+ <stem>.json with --json).")
@click.option("--cov", "cov_path", type=click.Path(dir_okay=False), default=None, help="Vision covariance side file [TRAJ stem.cov.csv].")
@click.option("--mode", type=click.Choice(["smoother", "filter"]), default=None,
              help="smoother: offline (RTS); filter: causal Kalman filter estimates [default: smoother].")
@click.option("--offset", nargs=3, type=float, default=None, metavar="E N H", help="Subtracted from easting,northing,height [the log's '# offset:'].")
@click.option("--lever", nargs=3, type=float, default=None, metavar="DX DY DZ",
              help="Camera position in the body frame, m (not estimated) [default: 0 0 0].")
@click.option("--mount-rotation", "mount_path", type=click.Path(dir_okay=False), default=None,
              help="Fixed R_body_cam (3x3 or quaternion file) instead of estimating the mount.")
@click.option("--model-to-world", "m2w_path", type=click.Path(dir_okay=False), default=None,
              help="Fixed 4x4 T_world_model instead of estimating it (e.g. a georeferenced model: identity).")
@click.option("--gps-sigma", nargs=2, type=float, default=None, metavar="H V", help="GPS noise, m [default: 3 5].")
@click.option("--ahrs-sigma", type=float, default=None, help="AHRS noise, deg [default: 3].")
@click.option("--vision-sigma", nargs=2, type=float, default=None, metavar="M DEG",
              help="Vision noise when no covariance file is given (x3 for SLAM frames) [default: 0.05 0.3].")
@click.option("--accel-sigma", type=float, default=None,
              help="With motion_model=cv (--set motion_model=cv): white acceleration, m/s^2/sqrt(Hz) [default: 1]; "
                   "the default model is constant acceleration (jerk_sigma_mps3, default 0.5).")
@click.option("--ang-accel-sigma", type=float, default=None,
              help="Motion model: white angular acceleration, deg/s^2/sqrt(Hz) [default: 2].")
@click.option("--time-offset", type=float, default=None,
              help="Seconds added to the log's times to put them on the video clock [default: 0].")
@click.option("--estimate-time-offset", is_flag=True, default=None,
              help="Estimate the clock offset (1-D search within --time-offset +- max_time_offset_s, default 1 s; "
                   "its std in --json).")
@click.option("--estimate-lever-arm", is_flag=True, default=None,
              help="Estimate the lever arm from the GPS (used when its std is below max_lever_std_m, default 5 cm; "
                   "--lever is then the start); its std in --json.")
@config_options()
@json_option
@quiet_option
@verbosity_options
def fuse(traj_path, nav_path, out, cov_path, mode, offset, lever, mount_path, m2w_path, gps_sigma, ahrs_sigma,
         vision_sigma, accel_sigma, ang_accel_sigma, time_offset, estimate_time_offset, estimate_lever_arm,
         config_file, set_values, as_json,
         quiet, verbose):
    """Fuse a vision trajectory with a GPS/AHRS log (robust Kalman smoother, calibration estimated).

    Estimates the model-to-world transform (yaw + translation), the camera mount rotation
    (absorbing a constant AHRS heading bias) and the GPS bias (random walk); Huber-robust to GPS
    multipath. Vision gaps (lost frames) are bridged by GPS/AHRS, GPS dropouts by vision.

    \b
    Outputs: OUT (TUM, camera pose in the model frame, every frame of the video's time range),
    <stem>.cov.csv (t, source vision|nav, 6x6 covariance: x y z m, rx ry rz rad model-frame
    perturbation), <stem>.json with --json (calibration, outlier counts, the effective "config";
    also on stdout).

    \b
    Examples:
      mst nav fuse --traj traj.txt --nav nav.csv -o fused.txt --json
      mst nav fuse --traj traj.txt --nav nav.csv -o causal.txt --mode filter --lever 0.1 0 -0.15
      mst nav fuse --traj traj.txt --nav nav.csv -o fused.txt --config noise.yaml --set huber_k=2
      mst nav fuse --traj traj.txt --nav nav.csv -o fused.txt --estimate-time-offset --json
    """
    from mst.pipeline.nav.fusion import FusionConfig
    from mst.pipeline.nav.run import fuse_nav_files

    setup_logging(quiet, verbose, "mst nav fuse")
    options = {"mode": mode, "lever_arm_m": lever, "gps_sigma_h_m": _pair(gps_sigma, 0),
               "gps_sigma_v_m": _pair(gps_sigma, 1), "ahrs_sigma_deg": ahrs_sigma,
               "vision_sigma_m": _pair(vision_sigma, 0), "vision_sigma_deg": _pair(vision_sigma, 1),
               "accel_sigma_mps2": accel_sigma, "ang_accel_sigma_dps2": ang_accel_sigma, "time_offset_s": time_offset,
               "estimate_time_offset": estimate_time_offset, "estimate_lever_arm": estimate_lever_arm}
    cfg = build_config(FusionConfig, config_file=config_file, set_values=set_values, section_name="nav_fuse",
                       options=options, flags=FUSE_FLAGS)
    summary, res = fuse_nav_files(traj_path, nav_path, out, cfg, cov_path=cov_path, offset=offset,
                                  mount_path=mount_path, m2w_path=m2w_path, write_json=as_json)
    c = res.calib
    info(f"fused {len(res.t)} frames ({int(res.has_vision.sum())} with vision, {int((~res.has_vision).sum())} bridged by nav); "
         f"mount yaw/pitch/roll {c['mount_ypr_deg'][0]:.2f} {c['mount_ypr_deg'][1]:.2f} {c['mount_ypr_deg'][2]:.2f} deg, "
         f"model-to-world yaw {c['world_yaw_deg']:.2f} deg (std {c['world_yaw_std_deg']:.2f}), "
         f"{res.stats['gps_outliers']} GPS outliers -> {out}", quiet)
    if c["lever_arm_std_m"] is not None:
        std = ", ".join(f"{v:.3f}" for v in c["lever_arm_std_m"])
        info(f"lever arm {'estimated' if c['lever_arm_estimated'] else 'NOT observable, kept'}: "
             f"{' '.join(f'{v:.3f}' for v in c['lever_arm_m'])} m (std {std} m)", quiet)
    if c["time_offset_estimated"]:
        info(f"log clock offset {c['time_offset_s']:+.3f} s (std {c['time_offset_std_s']:.3f} s)", quiet)
    if as_json:
        emit_json(summary)


@nav_group.command("plot")
@click.option("--fused", "estimate", required=True, type=click.Path(dir_okay=False),
              help="The fused trajectory (TUM, mst nav fuse), or any estimate.")
@click.option("--gt", "reference", required=True, type=click.Path(dir_okay=False), help="Reference trajectory (TUM).")
@click.option("--nav", "nav_path", required=True, type=click.Path(dir_okay=False), help="Navigation log (nav.csv).")
@click.option("--calib", "calib_path", type=click.Path(dir_okay=False), default=None,
              help="Calibration JSON of `mst nav fuse --json` (maps the log into the model frame).")
@click.option("--vision", "vision_path", type=click.Path(dir_okay=False), default=None,
              help="The vision trajectory (TUM, mst track) for its own series.")
@click.option("-o", "--output", "out", required=True, type=click.Path(dir_okay=False), help="PNG to write.")
@click.option("--t-max-diff", type=float, default=0.01, show_default=True,
              help="Seconds: poses match the reference's within this.")
@json_option
@quiet_option
@verbosity_options
def plot(estimate, reference, nav_path, calib_path, vision_path, out, t_max_diff, as_json, quiet, verbose):
    """Plot vision, GPS/AHRS and fused positions over time against a reference, and their yaw
    differences, with the vision gaps and the GPS dropouts shaded (the UAV paper's figure).

    \b
    Examples:
      mst nav plot --fused fused.txt --gt seq/gt.txt --nav seq/nav.csv --calib fused.json --vision traj.txt -o nav.png

    The numbers of the same comparison: `mst eval traj fused.txt gt.txt --nav nav.csv --nav-calib fused.json`.
    """
    from mst import atomic_output, check_outputs
    from mst.eval.traj.navtable import nav_figure, nav_table_from_files

    setup_logging(quiet, verbose, "mst nav plot")
    check_outputs([out], [estimate, reference, nav_path, calib_path, vision_path])
    tab = nav_table_from_files(estimate, reference, nav_path, calib_path, vision_path, t_max_diff)
    with atomic_output(out) as tmp:
        nav_figure(tmp, tab)
    info(f"wrote {out} ({', '.join(tab.columns)} against {reference})", quiet)
    if as_json:
        emit_json({"output": str(out), **tab.to_json()})
