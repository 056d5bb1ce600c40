"""The former home of model I/O, kept so that importers of ``mst.meshtools.io`` keep working while
the stages move: the readers and writers live in :mod:`mst.meshtools.formats` (one module per
format), polygon geometry in :mod:`mst.meshtools.polygons`, PLY in :mod:`mst.core.ply`.
New code imports those; this module only re-exports their public names.
"""

from mst.core.ply import PLY_TYPES
from mst.meshtools.formats import (
    MODEL_SUFFIXES,
    WRITE_SUFFIXES,
    load_model,
    load_triangles,
    read_cao,
    read_cityjson,
    read_obj,
    read_off,
    read_vrml,
    save_model,
    save_triangles,
)
from mst.meshtools.model import merge_models
from mst.meshtools.polygons import (
    bridge_holes,
    start_at_convex_corner,
    start_loops_at_convex_corners,
    triangulate_model,
    unbridge_faces,
)

__all__ = ["MODEL_SUFFIXES", "PLY_TYPES", "WRITE_SUFFIXES", "bridge_holes", "load_model", "load_triangles",
           "merge_models", "read_cao", "read_cityjson", "read_obj", "read_off", "read_vrml", "save_model",
           "save_triangles", "start_at_convex_corner", "start_loops_at_convex_corners", "triangulate_model",
           "unbridge_faces"]
