"""``mst synth``: render a synthetic colour/depth sequence of a model with ground truth (CPU raycasting)."""

from __future__ import annotations

import click

from mst.cli.common import (
    CONFIG_CLASSES,
    FINITE,
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

SCENARIOS = ("orbit", "corridor", "flyover", "uav", "fpv", "fast", "turntable", "carried", "leave", "occluder", "blackout")
CONFIG_CLASSES["mst synth"] = "mst.pipeline.synth.config:SynthConfig"  # for --show-config
#: SynthConfig fields whose option is not "--" + the field name with dashes
FLAGS = {"focal_px": "--focal", "rgb_noise": "--noise", "environment": "--no-environment", "aa_samples": "--aa",
         "nthreads": "--threads"}


def _check_not_inputs(out_dir, inputs) -> None:
    """Refuse an output folder whose sequence files (model.obj, scene.json, rgb/ ...) include an input.

    ``mst synth`` replaces those names in OUT (with --overwrite): a --model or --from-scene inside
    them would be overwritten or deleted.
    """
    from pathlib import Path

    from mst import InputError
    from mst.pipeline.synth import _OWNED

    out = Path(out_dir)
    if not out.is_dir():
        return
    for i in inputs:
        if i is None or not Path(i).exists():
            continue
        ri = Path(i).resolve()
        for name in _OWNED:
            target = (out / name).resolve()
            if ri == target or target in ri.parents:
                raise InputError(out / name, f"output would overwrite the input {i}")


@click.command("synth")
@click.argument("scenario", required=False, metavar="SCENARIO", type=click.Choice(SCENARIOS))
@click.option("--model", "model", type=click.Path(dir_okay=False), help="Model file (.obj .wrl .cao .off .ply .stl, CityJSON).")
@click.option("-o", "--out", "out_dir", required=True, type=click.Path(file_okay=False), help="Output sequence folder.")
@click.option("--from-scene", "from_scene", type=click.Path(dir_okay=False),
              help="Re-render exactly what a scene.json describes (its model.obj beside it); other options ignored.")
@click.option("--frames", type=int, default=None, help="Output frames [orbit 120, corridor 150, flyover 120, fast 60].")
@click.option("--fps", type=FINITE, default=None, help="Frame rate (gt.txt time = frame / fps) [default: 30].")
@click.option("--width", type=int, default=None, help="Image width, pixels [default: 640].")
@click.option("--height", type=int, default=None, help="Image height, pixels [default: 480].")
@click.option("--focal", "focal_px", type=FINITE, default=None, help="Focal length fx = fy, pixels [525 * width / 640].")
@click.option("--speed", type=FINITE, default=None, help="Camera speed, m/s [orbit: one turn per 12 s; corridor: "
              "the pass spans the sequence; flyover max(8, distance/4)].")
@click.option("--distance", type=FINITE, default=None, help="Camera-to-model distance in metres (flyover: height above "
              "the model) [model fills ~70% of the image height; flyover clamp(0.3 diag, 30, 150)].")
@click.option("--seed", type=int, default=None, help="Seed of textures and noise [default: 0].")
@click.option("--drop", type=int, default=None, help="Keep every N-th frame of the trajectory (large motion) [fast: 8, else 1].")
@click.option("--pitch", "pitch_deg", type=FINITE, default=None,
              help="uav/fpv: camera pitch below the horizon, degrees [uav 45, fpv 8].")
@click.option("--base", type=click.Choice(["orbit", "corridor", "flyover", "uav", "fpv"]), default=None,
              help="Base scenario of 'fast' [default: orbit].")
@click.option("--depth/--no-depth", default=None, help="Write depth/ (16-bit PNG mm + float32 .npy m) [default: on].")
@click.option("--depth-noise", type=click.Choice(["none", "kinect"]), default=None,
              help="Structured-light depth noise, quantisation and holes [default: none].")
@click.option("--noise", "rgb_noise", type=FINITE, default=None, help="Colour noise sigma, 8-bit levels [default: 2].")
@click.option("--motion-blur", type=int, default=None, help="Sub-frames averaged per frame (1 = off) [default: 1].")
@click.option("--model-texture", is_flag=True, default=None, help="Texture the model (default: flat, per-face shading).")
@click.option("--floor", type=click.Choice(["concrete", "tiles"]), default=None,
              help="Floor texture of orbit/corridor (flyover: terrain) [default: concrete].")
@click.option("--no-environment", "no_env", is_flag=True, help="Model alone in front of the sky (no ground or walls).")
@click.option("--click-noise", type=FINITE, default=None, help="Gaussian pixel noise on the clicks [default: 0].")
@click.option("--n-clicks", "n_clicks", type=int, default=None, help="Model corners in clicks.txt (>= 4) [default: 6].")
@click.option("--up", type=click.Choice(["z", "-z", "y", "-y", "x", "-x"]), default=None,
              help="The model's up axis [default: z].")
@click.option("--video", is_flag=True, default=None, help="Also write video.mp4 (mp4v, or H.264 with --video-codec h264).")
@click.option("--video-codec", type=click.Choice(["mp4v", "h264"]), default=None,
              help="Codec of video.mp4: h264 (H.264 through imageio-ffmpeg's libx264, as a UAV records) [mp4v].")
@click.option("--aa", "aa_samples", type=click.Choice(["0", "4", "8", "16"]), default=None,
              help="Sub-pixel rays per silhouette/crease pixel [default: 16].")
@click.option("--texture-size", type=int, default=None, help="Texture tile size, texels (a power of two) [default: 2048].")
@click.option("--threads", "nthreads", type=int, default=None, help="Ray-casting threads (0 = all) [default: 0].")
@click.option("--overwrite", is_flag=True, help="Replace the sequence files in a non-empty output folder.")
@click.option("--nav", "nav_log", is_flag=True, help="Also write nav.csv (simulated GPS/AHRS, --seed; see `mst nav simulate`).")
@config_options()
@json_option
@quiet_option
@verbosity_options
def synth(scenario, model, out_dir, from_scene, as_json, quiet, verbose, overwrite, nav_log, config_file, set_values,
          **opts):
    """Render a synthetic sequence with ground truth (CPU raycasting, no GPU or display).

    \b
    SCENARIO: orbit (circle the model, always in view), corridor (walk past it; it
    leaves the view for a stretch), flyover (UAV pass above it, pitched toward the
    facades), uav (survey UAV 30-120 m up, camera pitched 30-60 deg down, turning
    away from the block for a stretch), fpv (forward-looking camera passing the facades
    at 20-50 m), fast (any --base scenario keeping every --drop-th frame); turntable,
    carried, leave, occluder, blackout (pipeline/synth/dynamic.py: the object turns in a
    still room, is carried along a path, leaves the view and comes back moved, a slab
    sweeps in front of it, black and blurred frames; frames.csv holds the truth).

    \b
    Writes DIR/rgb/%06d.png, depth/%06d.png (uint16 mm) + .npy (float32 m),
    camera.json, gt.txt (TUM, camera pose in the model frame, t = frame/fps),
    cMo/%06d.txt, clicks.txt (frame 0: X Y Z u v), model.obj, scene.ply
    (model + environment), scene.json (reproduces the run), frames.csv.

    \b
    Examples:
      mst synth orbit --model samples/building_tin.obj -o seq/ --frames 60 --depth
      mst synth corridor --model part.obj -o corr/ --depth-noise kinect --video
      mst synth fast --base orbit --drop 10 --model m.obj -o fast/ --click-noise 1
      mst synth --from-scene seq/scene.json -o seq2/     # identical files
      mst synth orbit --model m.obj -o seq/ --config synth.yaml   # settings by name (SynthConfig)
    """
    from pathlib import Path

    from mst import InputError

    setup_logging(quiet, verbose, "mst synth")
    _check_not_inputs(out_dir, [model, from_scene, Path(from_scene).parent / "model.obj" if from_scene else None,
                                config_file])
    if from_scene:
        from mst.pipeline.synth import synthesize_from_scene

        total = None
        try:
            import json

            spec = json.loads(Path(from_scene).read_text())
            total = spec["resolved"]["frames"]
        except Exception:  # noqa: BLE001 - the stage reports a bad file properly
            pass
        with progress_bar(total, "synth", quiet or as_json) as advance:
            summary = synthesize_from_scene(from_scene, out_dir, progress=advance, overwrite=overwrite)
    else:
        if scenario is None:
            raise click.UsageError("SCENARIO is required (or --from-scene scene.json)")
        if not model:
            raise click.UsageError("--model is required")
        from mst.pipeline.synth import DEFAULT_FRAMES, SynthConfig, synthesize

        if not Path(model).is_file():
            raise InputError(model, "model file does not exist")
        if opts["aa_samples"] is not None:
            opts["aa_samples"] = int(opts["aa_samples"])
        opts["environment"] = False if opts.pop("no_env") else None
        cfg = build_config(SynthConfig, config_file=config_file, set_values=set_values, section_name="synth",
                           options=opts, flags={k: FLAGS.get(k, "--" + k.replace("_", "-")) for k in opts})
        total = cfg.frames if cfg.frames is not None else DEFAULT_FRAMES[scenario]
        with progress_bar(max(total, 0), f"synth {scenario}", quiet or as_json) as advance:
            summary = synthesize(scenario, model, out_dir, cfg, progress=advance, overwrite=overwrite)
    if nav_log:  # after the sequence is complete: default error model of `mst nav simulate`
        # the sequence's seed (with --from-scene: --seed, 0 by default, as before)
        nav_seed = (opts.get("seed") or 0) if from_scene else summary["config"]["seed"]
        from mst.pipeline.nav.log import NavSimConfig
        from mst.pipeline.nav.run import simulate_nav_files

        summary["nav"] = simulate_nav_files(Path(out_dir) / "gt.txt", Path(out_dir) / "nav.csv", NavSimConfig(seed=nav_seed))["nav"]
    if as_json:
        emit_json(summary)
    else:
        info(f"{summary['frames']} frames ({summary['scenario']}, {summary['width']}x{summary['height']}, "
             f"distance {summary['distance_m']:.2f} m) -> {summary['out_dir']}; "
             f"{summary['render_ms_per_frame']:.0f} ms/frame rendering, {summary['clicks']} clicks", quiet)
