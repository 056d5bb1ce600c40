"""Console rows of a trajectory comparison (they read :meth:`TrajResult.to_json`)."""

from __future__ import annotations


def report_rows(s: dict) -> list[list[str]]:
    """The main numbers as (metric, value) rows for the console table."""
    def f(v, nd=4):
        return "-" if v is None else f"{v:.{nd}f}"

    rows = [["associated poses", f"{s['associated']} (est {s['poses_estimate']}, ref {s['poses_reference']})"],
            ["alignment", f"{s['align']}" + (f" (scale {s['alignment']['scale']:.6f})" if s["align"] == "sim3" else "")]]
    a = s["ate"]
    rows.append(["ATE [m] rmse / mean / median / std / min / max",
                 " / ".join(f(a[k]) for k in ("rmse", "mean", "median", "std", "min", "max"))])
    if s["rotation_error_deg"]:
        r = s["rotation_error_deg"]
        rows.append(["rotation error [deg] rmse / mean / max", " / ".join(f(r[k], 3) for k in ("rmse", "mean", "max"))])
    for key, lab in (("rpe_frames", f"RPE {s['rpe_frames']['delta']} frame(s)"),
                     ("rpe_metres", f"RPE {s['rpe_metres']['delta_m']:g} m")):
        tr = s[key]["translation"]
        rr = s[key]["rotation_deg"]
        rows.append([f"{lab} [m] rmse / mean", f"{f(tr['rmse'])} / {f(tr['mean'])} ({tr['count']} pairs)"])
        if rr:
            rows.append([f"{lab} [deg] rmse / mean", f"{f(rr['rmse'], 3)} / {f(rr['mean'], 3)}"])
    g = s["gaps"]
    rows.append(["gaps (reference poses without estimate)",
                 f"{g['missing_reference_poses']} poses in {g['count']} range(s)"])
    return rows


def uav_rows(s: dict) -> list[list[str]]:
    """UAV-paper table rows: quantity, mean, std."""
    rows = []
    for k, lab in (("dX", "dX [m]"), ("dY", "dY [m]"), ("dZ", "dZ [m]"), ("dyaw", "d-yaw [deg]")):
        v = s["uav_table"][k]
        rows.append([lab, "-" if v is None else f"{v['mean']:.4f}", "-" if v is None else f"{v['std']:.4f}"])
    return rows
