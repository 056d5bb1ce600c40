"""The report's core: run folders in, the page (HTML text) and a typed summary out.

Sections of a run: Table 1 (c2m), the C2M histogram and the colour-mapped cloud views, the
trajectory against the reference (ΔX ΔY ΔZ Δψ, ATE/RPE, the figure), the per-frame status timeline,
the overlay strip, and the commands and configurations that produced it. A batch folder gets an
overview table and one section per sequence. A part that cannot be drawn (a file missing, an
unreadable summary) becomes a note in its place; the page is always complete.
"""

from __future__ import annotations

import json
import logging
import shlex
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mst.eval.report import figures
from mst.eval.report.config import ReportConfig
from mst.eval.report.html import Section, esc, image, note, page, pre, table
from mst.eval.report.sources import SUMMARIES, RunFiles, find_runs

log = logging.getLogger(__name__)


@dataclass
class Report:
    html: str
    runs: list[str]
    batch: bool
    sections: list[str]            #: the section titles, in page order
    images: int
    notes: list[str] = field(default_factory=list)
    config: ReportConfig = field(default_factory=ReportConfig)

    def to_json(self) -> dict[str, Any]:
        return {"runs": self.runs, "batch": self.batch, "sections": self.sections, "images": self.images,
                "bytes": len(self.html.encode()), "notes": self.notes, "config": self.config.to_dict()}


class _Parts:
    """The parts of one run, each drawn on its own: a failure is a note, never a broken page."""

    def __init__(self, run: RunFiles, cfg: ReportConfig, notes: list[str]):
        self.run, self.cfg, self.notes = run, cfg, notes
        self.images = 0

    def img(self, png: bytes | None, alt: str, width: int | None = None) -> str:
        if png is None:
            return note(f"{alt}: not available for this run")
        self.images += 1
        return image(png, alt, width)

    def guarded(self, what: str, fn) -> list[str]:
        try:
            return fn()
        except Exception as e:  # noqa: BLE001 - reported in the page, the rest is still drawn
            msg = f"{self.run.name}: {what}: {type(e).__name__}: {e}"
            log.info(msg)
            self.notes.append(msg)
            return [note(f"{what} could not be drawn: {type(e).__name__}: {e}")]


def _c2m_parts(p: _Parts) -> list[tuple[str, list[str]]]:
    from mst.eval.c2m.report import overall_rows, table1_rows

    s = p.run.summaries.get("c2m")
    data_box: dict[str, Any] = {}

    def table1() -> list[str]:
        if s is None:
            return [note("no c2m.json in this run")]
        rows = table1_rows(s)
        return [table(rows[0], rows[1:]), table(["statistic", "unsigned"] + (["signed"] if s.get("signed") else []),
                                                overall_rows(s)),
                f"<p>{esc(s.get('points_valid'))} points of {esc(s.get('cloud'))} against "
                f"{esc(s.get('mesh'))} ({esc(s.get('mesh_triangles'))} triangles)</p>"]

    def views() -> list[str]:
        data = figures.cloud_data(p.run, p.cfg)
        data_box["data"] = data
        out = [p.img(figures.c2m_histogram(p.run, data), "C2M histogram")] if s is not None else []
        if data is None:
            return out + [note("no cloud in this run")]
        return out + [p.img(figures.cloud_views(data, p.cfg), "cloud, top and side views")]

    return [("Table 1: cloud-to-mesh", p.guarded("Table 1", table1)),
            ("C2M histogram and cloud views", p.guarded("cloud views", views))]


def _traj_parts(p: _Parts) -> list[tuple[str, list[str]]]:
    from mst.eval.traj import report_rows, uav_rows

    ev = p.run.summaries.get("eval")

    def traj() -> list[str]:
        if ev is None:
            return [note("no eval.json in this run")]
        return [table(["ΔX ΔY ΔZ Δψ (estimate − reference)", "mean", "std"],
                      [[r[0].replace("dX", "ΔX").replace("dY", "ΔY").replace("dZ", "ΔZ").replace("d-yaw", "Δψ"),
                        *r[1:]] for r in uav_rows(ev)]),
                table(["metric", "value"], report_rows(ev)),
                p.img(figures.trajectory(p.run), "trajectory against the reference")]

    def status() -> list[str]:
        if p.run.traj_csv is None:
            return [note("no traj.csv in this run")]
        rows = figures.read_status(p.run.traj_csv)
        if not rows:
            return [note("traj.csv has no frames")]
        out = [p.img(figures.timeline(rows, p.cfg), "per-frame status timeline")]
        strip = figures.overlay_strip(p.run, rows, p.cfg)
        if strip:
            figs = "".join(f"<figure>{p.img(png, f'frame {i}', p.cfg.overlay_width_px)}"
                           f"<figcaption>frame {i}: {esc(st)}</figcaption></figure>" for i, st, png in strip)
            out += ["<h3>Overlay frames</h3>", f'<div class="strip">{figs}</div>']
        else:
            out.append(note("overlay strip: the frames, model or camera of the run are not known "
                            "(mst report --frames/--model/--camera)"))
        return out

    return [("Trajectory against the reference", p.guarded("trajectory", traj)),
            ("Per-frame status and overlay frames", p.guarded("status timeline", status))]


def _provenance(p: _Parts) -> list[tuple[str, list[str]]]:
    def parts() -> list[str]:
        out = []
        batch = any(e.get("argv") for e in p.run.states.values())  # a batch sequence: its state is the record
        if p.run.command_lines and not batch:
            out += ["<h3>Commands (commands.sh, in the order they ran)</h3>", pre("\n".join(p.run.command_lines))]
        elif p.run.commands:
            lines = [shlex.join(["mst", *p.run.commands[s]]) for s in SUMMARIES if s in p.run.commands]
            out += ["<h3>Commands</h3>", pre("\n".join(lines))]
        else:
            out.append(note("no commands recorded: mst batch records them (batch-state.json), make demo in "
                            "commands.sh; this run has neither"))
        for stage in SUMMARIES:
            cfg = (p.run.summaries.get(stage) or {}).get("config")
            if cfg is not None:
                out += [f"<h3>{esc(stage)} configuration (--config of it repeats the run)</h3>",
                        pre(json.dumps(cfg, indent=2, default=str))]
        return out

    return [("Commands and configurations", p.guarded("provenance", parts))]


def run_sections(run: RunFiles, cfg: ReportConfig, notes: list[str]) -> tuple[list[tuple[str, list[str]]], int]:
    p = _Parts(run, cfg, notes)
    parts = _c2m_parts(p) + _traj_parts(p) + _provenance(p)
    return parts, p.images


def _overview(runs: list[RunFiles]) -> Section:
    stages = ("init", "track", "fuse", "c2m", "eval")
    rows, errors = [], []
    for r in runs:
        cells = []
        for s in stages:
            e = r.states.get(s)
            cells.append("-" if e is None else e.get("status", "?"))
            if e is not None and e.get("status") == "failed":
                errors.append(f"{r.name}: {e.get('error')}")
        c2m = r.summaries.get("c2m") or {}
        ev = r.summaries.get("eval") or {}
        first = (c2m.get("thresholds") or [{}])[0]
        rows.append([r.name, *cells, "-" if not first else f"{first.get('percent', 0):.1f} % < {first.get('max_dist'):g} m",
                     "-" if not ev.get("ate") else f"{ev['ate']['rmse']:.4f}"])
    sec = Section("overview", "Batch overview").add(
        table(["sequence", *stages, "C2M (first threshold)", "ATE rmse [m]"], rows))
    if errors:
        sec.add("<h3>Failures</h3>", pre("\n".join(errors)))
    return sec


def build_report(run_dir: str | Path, cfg: ReportConfig | None = None, frames: str | None = None,
                 model: str | None = None, camera: str | None = None, fps: float | None = None) -> Report:
    """The report of a run folder or a batch folder (see the module docstring)."""
    from mst.eval.report.sources import read_run

    cfg = cfg or ReportConfig()
    runs, batch = find_runs(run_dir)
    if not batch and (frames or model or camera or fps is not None):
        runs = [read_run(runs[0].folder, frames, model, camera, fps)]
    notes: list[str] = []
    sections: list[Section] = [_overview(runs)] if batch else []
    images = 0
    for run in runs:
        parts, n = run_sections(run, cfg, notes)
        images += n
        if batch:
            sec = Section(f"run-{run.name}", run.name)
            for title, body in parts:
                sec.add(f"<h3>{esc(title)}</h3>", *body)
            sections.append(sec)
        else:
            sections += [Section(f"s{k}", title, body) for k, (title, body) in enumerate(parts)]
    name = Path(run_dir).resolve().name
    title = f"mst report: {'batch ' if batch else ''}{name}"
    sub = f"{len(runs)} sequence{'s' if len(runs) != 1 else ''} in {Path(run_dir).resolve()}"
    return Report(page(title, sub, sections), [r.name for r in runs], batch, [s.title for s in sections], images,
                  notes, cfg)
