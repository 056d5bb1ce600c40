"""mst.eval.report: ``mst report``: one self-contained HTML page of a run folder or a batch folder.

Holds: config (ReportConfig), sources (which files a run folder holds), figures (PNG images),
html (the page), build (core ``build_report``) and runner (``write_report``).
May import: numpy, OpenCV, matplotlib (lazily), mst.core, mst.errors, mst.meshtools, mst.eval.
"""
