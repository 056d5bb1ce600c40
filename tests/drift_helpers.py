"""Helpers of the drift-budget tests (test_slam_drift.py, test_slam_track.py): a tracking run with
per-frame errors relative to the budget's distance (the nearest model vertex) and the predicted
bound of each map pose."""

from __future__ import annotations

import csv
import json

import numpy as np

from mst.eval.bench.slam import trajectory_errors


def budget_track(seq, mode, out, budget: bool = True):
    """Track; per-frame status/errors (relative to the nearest model vertex, the budget's distance),
    the aid column and the predicted bound of each map pose."""
    from mst.pipeline.tracking import TrackConfig, run_track

    d = {"aid": mode}
    if not budget:  # calibration runs: every map pose output, its predicted bound logged
        d["slam"] = {"drift_budget_rel": 1e9, "drift_budget_deg": 1e9}
    s = run_track(seq / "rgb", seq / "model.obj", seq / "camera.json", seq / "cMo" / "000000.txt", out,
                  TrackConfig.from_dict(d), depth_dir=seq / "depth" if mode == "rgbd" else None, fps=30.0,
                  write_json=True)
    return s, budget_errors(seq, out)


def budget_errors(seq, out) -> dict:
    """:func:`budget_track`'s per-frame errors of the run written to ``out`` (its .csv and .json)."""
    from mst.core.trajectory import read_tum
    from mst.meshtools.formats import load_model

    e = trajectory_errors(seq, out)
    _, Tg = read_tum(seq / "gt.txt")
    V = np.asarray(load_model(seq / "model.obj").vertices, float)
    dist = np.linalg.norm(Tg[e["frame"], None, :3, 3] - V[None], axis=2).min(1)
    e["rel"] = e["rel"] * np.linalg.norm(Tg[e["frame"], :3, 3] - _centre(seq), axis=1) / dist
    unc = json.loads(out.with_suffix(".json").read_text()).get("slam_uncertainty", {})
    e["pred"] = np.array([unc.get(str(f), [np.nan, np.nan]) for f in e["frame"]], float)
    e["aid"] = np.array([r["aid"] for r in csv.DictReader(open(out.with_suffix(".csv")))])
    return e


def _centre(seq):
    from mst.eval.bench.slam import model_centre

    return model_centre(seq)


def calibrated_share(e) -> float:
    """Share of the output map poses whose predicted bound covers the measured error (both parts)."""
    sl = (e["status"] == "slam") & np.isfinite(e["pred"][:, 0])
    assert sl.sum() >= 10
    return float(((e["pred"][sl, 0] >= e["rel"][sl]) & (e["pred"][sl, 1] >= e["deg"][sl])).mean())
