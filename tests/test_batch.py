"""mst batch: six small synthetic sequences on a LocalCluster (2 workers), resume, reruns by content,
bad manifests (one line each, nothing written), and a real scheduler + worker started as processes."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import ROOT, run_mst
from dask_helpers import fast_local_workers

HOUSE = ROOT / "samples" / "building_tin.obj"
BOX = """v -1 -0.75 0\nv 1 -0.75 0\nv 1 0.75 0\nv -1 0.75 0\nv -1 -0.75 1.2\nv 1 -0.75 1.2\nv 1 0.75 1.2
v -1 0.75 1.2\nf 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 2 3 7\nf 2 7 6\nf 3 4 8\nf 3 8 7
f 4 1 5\nf 4 5 8\n"""
SMALL = ["--frames", "5", "--width", "320", "--height", "240", "--aa", "0", "--texture-size", "256", "-q",
         "--seed", "1"]


def _seq(name: str, data: str, model: str, **kw) -> dict:
    d = {"name": name, "frames": f"{data}/rgb", "model": model, "camera": f"{data}/camera.json",
         "clicks": f"{data}/clicks.txt", "gt": f"{data}/gt.txt"}
    if kw.pop("depth", True):
        d.update(depth=f"{data}/depth", reference=f"{data}/scene.ply")
    d.update(kw)
    return d


@pytest.fixture(scope="module")
def campaign(tmp_path_factory) -> Path:
    """Two models x two scenarios (orbit; fast = every 3rd frame), 320x240, 5 frames, and a manifest of
    six sequences: those four, one more on the house orbit (edges only, no depth) and one broken
    (two clicks)."""
    import yaml

    root = tmp_path_factory.mktemp("campaign")
    (root / "box.obj").write_text(BOX)
    for model, mname in ((str(HOUSE), "house"), ("box.obj", "box")):
        run_mst("synth", "orbit", "--model", model, "-o", root / f"{mname}-orbit", *SMALL, cwd=root)
        run_mst("synth", "fast", "--drop", "3", "--model", model, "-o", root / f"{mname}-fast", *SMALL, cwd=root)
    lines = (root / "box-orbit" / "clicks.txt").read_text().splitlines()
    (root / "two-clicks.txt").write_text("\n".join([x for x in lines if not x.startswith("#")][:2]) + "\n")
    seqs = [_seq("house-orbit", "house-orbit", str(HOUSE)), _seq("house-fast", "house-fast", str(HOUSE)),
            _seq("box-orbit", "box-orbit", "box.obj"), _seq("box-fast", "box-fast", "box.obj"),
            _seq("house-edges", "house-orbit", str(HOUSE), depth=False, options={"track": {"slam": "off"}}),
            _seq("broken", "box-orbit", "box.obj", depth=False, clicks="two-clicks.txt")]
    manifest = {"defaults": {"fps": 30, "options": {"eval": {"align": "none"}, "c2m.thresholds": "0.02,0.05,0.1"}},
                "sequences": seqs}
    (root / "batch.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False))
    return root


def _batch(root: Path, *args) -> tuple[int, dict, str]:
    """``mst batch`` on the campaign (its local workers from the preloaded fork server)."""
    with fast_local_workers():
        r = run_mst("batch", root / "batch.yaml", "-o", root / "out", "--json", *(args or ("--workers", "2")),
                    check=False)
    return r.returncode, (json.loads(r.stdout) if r.stdout.strip() else {}), r.stderr


def _ran(summary: dict) -> dict[str, list[str]]:
    """sequence -> the stages that ran (status ok) in this call."""
    return {s["name"]: [k for k, v in s["stages"].items() if v["status"] == "ok"] for s in summary["sequences"]}


def test_batch_six_sequences_resume_and_rerun_by_content(campaign):
    code, res, err = _batch(campaign)
    assert code == 1, err
    by = {s["name"]: s for s in res["sequences"]}
    assert [n for n, s in by.items() if s["status"] == "ok"] == ["house-orbit", "house-fast", "box-orbit",
                                                                   "box-fast", "house-edges"]
    broken = by["broken"]
    assert broken["status"] == "failed" and "two-clicks.txt" in broken["error"] and "\n" not in broken["error"]
    assert broken["stages"]["track"]["status"] == "blocked"
    assert "broken: mst init: error:" in err and "1 of 6 sequences failed" in err
    assert set(res["models"]) == {"models/building_tin", "models/box"}  # converted once per model
    out = campaign / "out"
    for name in ("house-orbit", "box-fast"):
        for f in ("pose0.txt", "traj.txt", "traj.csv", "cloud.ply", "c2m.json", "c2m_hist.png", "eval.json"):
            assert (out / name / f).is_file(), (name, f)
        assert json.loads((out / name / "c2m.json").read_text())["config"]["thresholds_m"] == [0.02, 0.05, 0.1]
    assert not (out / "house-edges" / "cloud.ply").exists()
    assert res["config"]["workers"] == 2

    # a rerun: nothing runs (no cluster is even started); the broken sequence reports its recorded error
    code, res2, _ = _batch(campaign)
    assert code == 1 and res2["stage_counts"]["ok"] == 0 and res2["scheduler"] is None
    assert {s["name"]: s["error"] for s in res2["sequences"]}["broken"] == broken["error"]

    # a changed camera file (same camera, other bytes) reruns only what reads it
    cam = campaign / "box-orbit" / "camera.json"
    cam.write_text(json.dumps(json.loads(cam.read_text())))
    code, res3, err3 = _batch(campaign, "--workers", "1")
    assert res3, err3
    ran = _ran(res3)
    assert ran["box-orbit"][:3] == ["init", "track", "fuse"]
    assert all(not v for k, v in ran.items() if k != "box-orbit")
    assert all(m["status"] == "skipped" for m in res3["models"].values())
    assert {s["name"]: s["status"] for s in res3["sequences"]}["box-orbit"] == "ok"


def _bad(tmp_path: Path, manifest: dict | str, *args) -> str:
    import yaml

    p = tmp_path / ("m.csv" if isinstance(manifest, str) else "m.yaml")
    p.write_text(manifest if isinstance(manifest, str) else yaml.safe_dump(manifest))
    r = run_mst("batch", p, "-o", tmp_path / "out", *args, check=False)
    assert r.returncode == 1 and not (tmp_path / "out").exists(), r.stderr
    lines = [x for x in r.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("mst batch: error:"), r.stderr
    return lines[0]


@pytest.fixture
def one_seq(tmp_path) -> dict:
    for f in ("cam.json", "clicks.txt", "m.obj"):
        (tmp_path / f).write_text("x\n")
    (tmp_path / "rgb").mkdir()
    return {"name": "a", "frames": "rgb", "model": "m.obj", "camera": "cam.json", "clicks": "clicks.txt"}


def test_bad_manifests_one_line_nothing_written(tmp_path, one_seq):
    msg = _bad(tmp_path, {"sequences": [{**one_seq, "camera": "nope.json"}]})
    assert "m.yaml" in msg and "sequence 'a'" in msg and "camera nope.json does not exist" in msg
    msg = _bad(tmp_path, {"sequences": [one_seq, {**one_seq}]})
    assert "sequences 1 and 2 are both named 'a'" in msg
    msg = _bad(tmp_path, {"sequences": [{**one_seq, "options": {"track": {"warp-speed": 9}}}]})
    assert "unknown option --warp-speed of mst track" in msg
    msg = _bad(tmp_path, {"sequences": [{**one_seq, "options": {"track": {"model": "x.obj"}}}]})
    assert "--model of mst track is set by the batch" in msg
    msg = _bad(tmp_path, {"sequences": [{**one_seq, "options": {"track.range": "wide"}}]})
    assert "--range" in msg and "wide" in msg
    msg = _bad(tmp_path, {"sequences": [{**one_seq, "colour": "red"}]})
    assert "unknown key 'colour'" in msg
    msg = _bad(tmp_path, "name,frames,model,camera,clicks\na,rgb,m.obj,cam.json,missing.txt\n")
    assert "m.csv" in msg and "clicks missing.txt does not exist" in msg


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_unreachable_scheduler_and_a_setting_from_a_config_file(tmp_path, one_seq):
    port = _free_port()
    cfg = tmp_path / "batch.yaml"
    cfg.write_text(f"batch:\n  scheduler: tcp://127.0.0.1:{port}\n  connect_timeout_s: 0.5\n")
    msg = _bad(tmp_path, {"sequences": [one_seq]}, "--config", cfg)
    assert f"cannot reach the dask scheduler at tcp://127.0.0.1:{port} (within 0.5 s)" in msg
    cfg.write_text("batch:\n  worker: 3\n")
    msg = _bad(tmp_path, {"sequences": [one_seq]}, "--config", cfg)
    assert "worker: unknown key" in msg


def test_csv_manifest_equals_yaml(tmp_path, one_seq):
    import yaml

    from mst.cli.batch import stage_command
    from mst.eval.batch.manifest import load_manifest

    (tmp_path / "m.yaml").write_text(yaml.safe_dump({"sequences": [{**one_seq, "fps": 30,
                                                                     "options": {"track": {"range": 8, "klt": False}}}]},
                                                    sort_keys=False))
    (tmp_path / "m.csv").write_text("name,frames,model,camera,clicks,fps,track.range,track.klt\n"
                                    "a,rgb,m.obj,cam.json,clicks.txt,30,8,false\n")
    a, b = load_manifest(tmp_path / "m.yaml", stage_command), load_manifest(tmp_path / "m.csv", stage_command)
    assert a.sequences == b.sequences
    assert a.sequences[0].options["track"].args == ("--range", "8", "--no-klt")
    # YAML 1.1's boolean words: a flag takes them, a choice keeps ``off`` as the word it is
    (tmp_path / "w.yaml").write_text("sequences:\n  - {name: a, frames: rgb, model: m.obj, camera: cam.json, "
                                     "clicks: clicks.txt, options: {track: {klt: no, slam: off}}}\n")
    (tmp_path / "w.csv").write_text("name,frames,model,camera,clicks,track.klt,track.slam\n"
                                    "a,rgb,m.obj,cam.json,clicks.txt,off,off\n")
    for f in ("w.yaml", "w.csv"):
        assert load_manifest(tmp_path / f, stage_command).sequences[0].options["track"].args == (
            "--no-klt", "--slam", "off"), f


@pytest.mark.slow
def test_a_real_scheduler_and_worker_as_processes(campaign, tmp_path):
    """`dask scheduler` and `dask worker` started as separate processes; the same manifest via --scheduler."""
    port = _free_port()
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (os.environ.get("PYTHONPATH"), ) if p)}
    addr = f"tcp://127.0.0.1:{port}"
    procs = [subprocess.Popen([*dask, "--host", "127.0.0.1", "--port", str(port), "--dashboard-address", ":0"],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        procs.append(subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_worker", addr, "--nthreads", "1",
                                       "--nworkers", "2", "--no-dashboard"], env=env, stdout=subprocess.DEVNULL,
                                      stderr=subprocess.DEVNULL, cwd=tmp_path))
        from dask.distributed import Client

        with Client(addr, timeout=60) as c:
            c.wait_for_workers(2, timeout=60)
        r = run_mst("batch", campaign / "batch.yaml", "-o", tmp_path / "out", "--scheduler", addr, "--json", check=False)
        res = json.loads(r.stdout)
        assert r.returncode == 1 and res["scheduler"] == addr
        assert [s["name"] for s in res["sequences"] if s["status"] == "failed"] == ["broken"]
        assert res["stage_counts"]["ok"] >= 20
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            p.wait(timeout=30)
