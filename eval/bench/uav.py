"""UAV survey tracking speed (issue 11): median per-frame time of ``mst track`` in the default mode
(edges + KLT, mono SLAM aid on standby, no far plane) on city models, at 640x480 and 1280x720.

Models: the largest shared CityJSON set (``rotterdam_subset.json``, converted with
``mst convert-model`` as a user would; skipped when ../shared/data is absent) and a 50,000-polygon
procedural city (:func:`mst.meshtools.generate.city_block_model`, 7,710 buildings, about 2.8 km
square). Sequence: ``mst synth flyover`` (the default height above the roofs: clamp(0.3 x diagonal,
30, 150) m), 40 frames, first pose from the clicks. The time is ``run_track``'s own per-frame clock
(decoding excluded: the median of ``ms`` in traj.csv), so the first frame's set-up is not in the
median. Targets: median <= 10 ms at 640x480, <= 20 ms at 1280x720.
"""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SHARED = ROOT.parent / "shared" / "data"
TARGET_MS = {(640, 480): 10.0, (1280, 720): 20.0}
FRAMES = 40


def _cli(*args) -> None:
    from mst.cli.main import main

    try:
        main([str(a) for a in args])
    except SystemExit as e:
        if e.code:
            raise RuntimeError(f"mst {' '.join(map(str, args))} failed ({e.code})") from None


def _bench(name: str, model: Path, workdir: Path, size: tuple[int, int], convert: bool) -> dict:
    from mst.pipeline.tracking import TrackConfig, run_track

    w, h = size
    d = workdir / f"{name}_{w}x{h}"
    seq = d / "seq"
    d.mkdir(parents=True, exist_ok=True)
    _cli("synth", "flyover", "--model", model, "-o", seq, "--frames", FRAMES, "--width", w, "--height", h,
         "--no-depth", "--aa", 4, "--texture-size", 512, "-q", "--overwrite")
    m = d / "m.wrl"
    if convert:
        _cli("convert-model", seq / "model.obj", "-o", m, "-q")
    else:
        m = model
    _cli("init", "--model", m, "--camera", seq / "camera.json", "--clicks", seq / "clicks.txt", "-o", d / "p0.txt", "-q")
    s = run_track(seq / "rgb", m, seq / "camera.json", d / "p0.txt", d / "traj.txt", TrackConfig(), fps=30)
    target = TARGET_MS[size]
    return {"bench": f"uav track default {name} {w}x{h}", "frames": s["frames"], "tracked": s["tracked"],
            "median_ms": float(s["median_ms"]), "p95_ms": float(s["p95_ms"]),
            "target": f"median <= {target:g} ms, every frame tracked",
            "ok": bool(s["median_ms"] <= target and s["tracked"] == s["frames"])}


def run(workdir: Path, sizes=((640, 480), (1280, 720))) -> list[dict]:
    from mst.meshtools.formats import save_model
    from mst.meshtools.generate import city_block_model

    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    rows = []
    city = workdir / "city50k.wrl"
    m = city_block_model(7710)
    save_model(city, m)
    rot = SHARED / "cityjson" / "rotterdam_subset.json"
    for size in sizes:
        if rot.is_file():
            rows.append(_bench("rotterdam", rot, workdir, size, convert=True))
        r = _bench(f"city{m.n_faces // 1000}k", city, workdir, size, convert=False)
        r["polygons"] = m.n_faces
        rows.append(r)
    return rows
