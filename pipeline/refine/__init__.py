"""Offline global refinement of a tracked trajectory against the model (``mst refine``).

Holds: the settings (:class:`RefineConfig`), depth back-projection, model sampling and robust
point-to-plane ICP (Open3D, imported lazily), the keyframe pose graph (scipy), the runner.
May import mst.core, mst.meshtools and mst.pipeline (depth_io, fusion's time-to-frame rule).
"""

from mst.pipeline.refine.config import RefineConfig

__all__ = ["RefineConfig", "refine"]


def __getattr__(name):
    if name == "refine":
        from mst.pipeline.refine.runner import refine

        return refine
    raise AttributeError(name)
