"""mst.eval.batch: ``mst batch``: a manifest of sequences run as a dask.distributed task graph, resumable.

Holds: config (BatchConfig), manifest (YAML/CSV -> sequences), plan (the stages of each sequence),
state (content hashes, the per-folder state file), execute (one stage, run on a worker), runner (the graph).
May import: mst.core, mst.errors, mst (atomic outputs), click, dask.distributed (lazily); never mst.cli:
the command layer passes the functions that check and run the ``mst`` commands (mst.cli.batch).
"""
