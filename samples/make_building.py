"""Write samples/building_tin.obj: a small gabled house as a TIN (4 m x 3 m, eaves 2.4 m, ridge 3.8 m).

Every planar face of the house is cut into 4 triangles (``split=2``), like a triangulated city model.
Run from the repository root: ``python samples/make_building.py``.
"""

from pathlib import Path

from mst.meshtools.generate import gabled_house
from mst.meshtools.io import save_triangles

V, F = gabled_house(split=2, length=4.0, width=3.0, eaves=2.4, ridge=1.4)
out = Path(__file__).resolve().parent / "building_tin.obj"
save_triangles(out, V, F)
print(f"{out}: {len(V)} vertices, {len(F)} triangles")
