"""Write samples/building_tin.obj: a small L-shaped house with a cross-gabled roof, as a TIN.

Footprint: wing A 5.0 m along x by 2.5 m, wing B 2.5 m wide reaching 4.0 m along y (they share the
2.5 m corner square); eaves at 2.2 m, both ridges at 3.5 m (wing A's along x, wing B's along y),
crossing over the corner square, with hips and valleys on its diagonals: the roof is the upper
envelope of two gabled prisms. z up, metres, outward winding. Every planar face is cut into 4
triangles (``split=2``), like a triangulated city model.

Run from the repository root: ``python samples/make_building.py``.
"""

from pathlib import Path

import numpy as np

from mst.meshtools.formats import save_triangles
from mst.meshtools.generate import model_to_tin
from mst.meshtools.model import PolygonModel

a, b, w = 5.0, 4.0, 2.5          # wing A length (x), wing B length (y), wing width
e, R = 2.2, 3.5                  # eaves and ridge heights
h = w / 2

faces_xyz = [
    # walls, counter-clockwise seen from outside
    [(0, 0, 0), (a, 0, 0), (a, 0, e), (w, 0, e), (h, 0, R), (0, 0, e)],            # south (y = 0), B's gable
    [(a, 0, 0), (a, w, 0), (a, w, e), (a, h, R), (a, 0, e)],                         # east gable of A
    [(a, w, 0), (w, w, 0), (w, w, e), (a, w, e)],                                    # north wall of A
    [(w, w, 0), (w, b, 0), (w, b, e), (w, w, e)],                                    # east wall of B
    [(w, b, 0), (0, b, 0), (0, b, e), (h, b, R), (w, b, e)],                         # north gable of B
    [(0, b, 0), (0, 0, 0), (0, 0, e), (0, h, R), (0, w, e), (0, b, e)],             # west (x = 0), A's gable
    [(0, 0, 0), (0, b, 0), (w, b, 0), (w, w, 0), (a, w, 0), (a, 0, 0)],             # floor (seen from below)
    # roof: wing A slopes (facing -y and +y), wing B slopes (facing -x and +x)
    [(0, 0, e), (h, h, R), (0, h, R)],                                               # A south, west piece
    [(w, 0, e), (a, 0, e), (a, h, R), (h, h, R)],                                    # A south, east piece
    [(0, h, R), (h, h, R), (0, w, e)],                                               # A north, west piece
    [(h, h, R), (a, h, R), (a, w, e), (w, w, e)],                                    # A north, east piece
    [(0, 0, e), (h, 0, R), (h, h, R)],                                               # B west, south piece
    [(h, h, R), (h, b, R), (0, b, e), (0, w, e)],                                    # B west, north piece
    [(h, 0, R), (w, 0, e), (h, h, R)],                                               # B east, south piece
    [(h, h, R), (w, w, e), (w, b, e), (h, b, R)],                                    # B east, north piece
]

index: dict[tuple, int] = {}
faces = []
for f in faces_xyz:
    faces.append([index.setdefault(tuple(map(float, p)), len(index)) for p in f])
V = np.array(sorted(index, key=index.get), float)
V_tin, F_tin = model_to_tin(PolygonModel(V, faces), split=2)
out = Path(__file__).resolve().parent / "building_tin.obj"
save_triangles(out, V_tin, F_tin)
print(f"{out}: {len(V_tin)} vertices, {len(F_tin)} triangles")
