"""Reports of a C2M result: Table 1 of the RGB-D paper (rows, CSV) and the overall statistics, as
console rows and Markdown. They read the JSON form of the result (:meth:`C2MResult.to_json`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def table1_rows(summary: dict) -> list[list[str]]:
    """Table 1 of the RGB-D paper as rows of strings (label, one column per threshold).

    Means and standard deviations use the paper's 2 decimals for thresholds >= 0.1 m and one more
    decimal per decade below (a 0.01 m threshold prints 3), so centimetre tables stay readable.
    """
    t = summary["thresholds"]
    smallest = min((r["max_dist"] for r in t if r["max_dist"] > 0), default=0.1)
    nd_m = max(2, 1 - int(np.floor(np.log10(smallest) + 1e-9)))

    def f(v, nd):
        return "-" if v is None else f"{v:.{nd}f}"

    return [
        ["Max. C2M distance [m]"] + [f"{r['max_dist']:g}" for r in t],
        ["% of points less than max. distance"] + [f(r["percent"], 1) for r in t],
        ["Mean C2M dist. [m]"] + [f(r["mean"], nd_m) for r in t],
        ["Std. Dev. C2M dist. [m]"] + [f(r["std"], nd_m) for r in t],
    ]


def table1_csv(summary: dict) -> str:
    """Table 1 as CSV, full precision."""
    t = summary["thresholds"]

    def f(v):
        return "" if v is None else repr(float(v))

    rows = [["Max. C2M distance [m]"] + [f(r["max_dist"]) for r in t],
            ["% of points less than max. distance"] + [f(r["percent"]) for r in t],
            ["Mean C2M dist. [m]"] + [f(r["mean"]) for r in t],
            ["Std. Dev. C2M dist. [m]"] + [f(r["std"]) for r in t]]
    return "".join(",".join(r) + "\n" for r in rows)


def overall_rows(summary: dict) -> list[list[str]]:
    """Overall statistics rows: (statistic, unsigned[, signed])."""
    keys = ["count", "mean", "median", "std", "rms", "min", "max"]
    rows = []
    for k in keys:
        u = summary["unsigned"][k]
        r = [k if k == "count" else f"{k} [m]", str(u) if k == "count" else ("-" if u is None else f"{u:.6f}")]
        if summary.get("signed"):
            s = summary["signed"][k]
            r.append(str(s) if k == "count" else ("-" if s is None else f"{s:.6f}"))
        rows.append(r)
    return rows


def markdown_report(summary: dict) -> str:
    """Table 1 and the overall statistics as Markdown."""
    rows = table1_rows(summary)
    n = len(rows[0])
    lines = [f"# C2M: {Path(summary['cloud']).name} vs {Path(summary['mesh']).name}", "",
             "| " + " | ".join(rows[0]) + " |", "|" + "---|" * n]
    lines += ["| " + " | ".join(r) + " |" for r in rows[1:]]
    lines += ["", f"Points: {summary['points_total']} total, {summary['points_valid']} valid, "
              f"{summary['points_nonfinite']} NaN/inf excluded"
              + (f", {summary['points_beyond_max_dist']} beyond max-dist {summary['max_dist']} m" if summary["max_dist"] else "")
              + f". Mesh: {summary['mesh_triangles']} triangles.", ""]
    hdr = ["statistic", "unsigned"] + (["signed"] if summary.get("signed") else [])
    lines += ["| " + " | ".join(hdr) + " |", "|" + "---|" * len(hdr)]
    lines += ["| " + " | ".join(r) + " |" for r in overall_rows(summary)]
    return "\n".join(lines) + "\n"
