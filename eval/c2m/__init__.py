"""mst.eval.c2m: cloud-to-mesh (C2M) distances and the Table-1 statistics of ``mst c2m``.

Holds: geometry, grids (+ numba kernels), distances, stats, driver (core ``c2m``), runner (``run_c2m``), report, config,
tiles (many tiles on dask). May import: numpy, numba, Open3D and dask.distributed (lazily), mst.core, mst.errors, mst.meshtools (mesh files), mst.eval.cloud_io.

Distance: for every cloud point, the exact Euclidean distance (metres, float64) to the nearest
triangle of the mesh, like CloudCompare's C2M. How it is computed:

1. A float64 global shift (the mesh bounding-box centre) is subtracted from mesh and cloud, so
   georeferenced coordinates (1e6 m) keep their precision; nothing below runs on raw coordinates.
2. The nearest triangle of each point is found by the compiled grid engine (default, ``engine="grid"``,
   numba, exact float64, no Open3D): meshes up to ``small_mesh_triangles`` triangles use a dense grid
   of lazily computed per-cell candidate lists; larger meshes bin every triangle into the cells its
   bounding box overlaps and search shells of cells around each point until the best distance is at
   most the distance to the cells not yet searched (exact, ties included); points far outside the
   grid scan the occupied cells. ``engine="bvh"`` uses Open3D's ``RaycastingScene`` BVH (float32 on
   the shifted coordinates) instead, followed by step 3.
3. (BVH engine) The distance to the picked triangle is recomputed exactly in float64 (Ericson's
   closest point on a triangle, vectorised), and when the closest point lies on an edge or vertex the
   triangles around that vertex are checked too, so a float32 near-tie cannot pick a farther triangle.
   Points farther than 100 mesh extents (where float32 picks degrade) are searched again exactly. A
   float32 BVH can still miss the nearest triangle by about 1e-6 m for points metres away from a
   wide flat region; the grid engine has no such error.

Sign (``signed=True``): positive on the side the triangle normals point to (outside of a closed
mesh wound counter-clockwise seen from outside), negative inside. The normal used is the
angle-weighted pseudo-normal of the nearest *feature* (Baerentzen & Aanaes 2005): the face normal
when the closest point is inside a triangle, the sum of the two adjacent face normals when it is on
an edge, the angle-weighted sum of the incident face normals when it is on a vertex. This is exact
for closed, consistently oriented meshes, also near edges and corners (where using the face normal
of the nearest triangle, as CloudCompare does, gives wrong signs). Duplicate vertices (same
coordinates) are merged for the topology, so split-vertex OBJ/STL files work.

Statistics (all in metres): for each threshold ``t`` of ``thresholds_m``, the percentage of valid points
with distance ``< t`` and the mean and population standard deviation of those distances (Table 1 of
the RGB-D paper); overall count, mean, median, std (population), RMS, min and max, unsigned and, with
``signed=True``, signed. Points with NaN/inf coordinates are counted and excluded. With ``max_dist_m``,
points farther than it from the mesh are counted as ``points_beyond_max_dist``, get NaN distance in the
output cloud, and are excluded from the overall statistics (they still count in the Table-1
denominators: they are not under any threshold <= max_dist).
"""

from mst.eval.c2m.config import DEFAULT_THRESHOLDS, C2MConfig
from mst.eval.c2m.distances import point_distances
from mst.eval.c2m.driver import MAX_CLOUD_COORD_M, C2MResult, C2MTiming, c2m, stream_distances
from mst.eval.c2m.geometry import MeshIndex, closest_point_on_triangles, prepare_mesh, triangle_distances
from mst.eval.c2m.report import markdown_report, overall_rows, table1_csv, table1_rows
from mst.eval.c2m.runner import load_mesh_triangles, run_c2m
from mst.eval.c2m.stats import DistanceStats, ThresholdRow

__all__ = [
    "DEFAULT_THRESHOLDS", "MAX_CLOUD_COORD_M", "C2MConfig", "C2MResult", "C2MTiming", "DistanceStats", "MeshIndex",
    "ThresholdRow", "c2m", "closest_point_on_triangles", "load_mesh_triangles", "markdown_report", "overall_rows",
    "point_distances", "prepare_mesh", "run_c2m", "stream_distances", "table1_csv", "table1_rows",
    "triangle_distances",
]
