"""Property-based tests (hypothesis) of every model, mesh, cloud, pose and trajectory reader/writer.

Two properties:

* **round trip**: write -> read gives back what was written (exactly for the formats that write
  shortest round-trip decimals or binary float64; within the format's stated precision otherwise);
* **robustness**: any mutation of a valid file (byte flips, truncation, inserted garbage tokens or
  bytes, deleted or duplicated spans) makes the reader either succeed or raise ``mst.InputError``:
  never another exception, never a numpy RuntimeWarning.

Every test is derandomized (fixed seed), so the suite is reproducible; example counts are small
enough that the whole module runs in a few seconds.
"""

from __future__ import annotations

import itertools
import re
import tempfile
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mst import InputError
from mst.core.poses import inv_T, make_T, read_rigid_transform, so3_exp
from mst.core.trajectory import read_pose_file, read_trajectory, read_tum, write_pose_file, write_tum
from mst.eval.cloud_io import read_cloud, write_cloud
from mst.meshtools import generate as gen
from mst.meshtools.formats import load_model, load_triangles, save_model, save_triangles
from mst.meshtools.model import PolygonModel

SETTINGS = dict(derandomize=True, deadline=None, database=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much])
_TMP = Path(tempfile.mkdtemp(prefix="mst-props-"))
_counter = itertools.count()


def _tmpfile(name: str) -> Path:
    d = _TMP / str(next(_counter))
    d.mkdir()
    return d / name


# ====================================================================== strategies
coords = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False, width=64)
names = st.one_of(st.none(), st.from_regex(r"[A-Za-z]([A-Za-z0-9_ ]{0,6}[A-Za-z0-9])?", fullmatch=True))


@st.composite
def polygon_models(draw, with_primitives: bool = False):
    """Random polygon models: faces of 3..7 distinct vertex indices, optional names, lines and
    (for .cao) cylinders and circles."""
    n = draw(st.integers(4, 24))
    V = np.array(draw(st.lists(st.tuples(coords, coords, coords), min_size=n, max_size=n)), np.float64)
    n_f = draw(st.integers(1, 8))
    faces = [np.array(draw(st.lists(st.integers(0, n - 1), min_size=3, max_size=7, unique=True)), np.int64)
             for _ in range(n_f)]
    nm = [draw(names) for _ in range(n_f)]
    lines = np.array(draw(st.lists(st.tuples(st.integers(0, n - 1), st.integers(0, n - 1)), max_size=4)),
                     np.int64).reshape(-1, 2)
    cyl, circ = [], []
    if with_primitives:
        # a cylinder's axis has a length (two coincident axis points are refused as bad input)
        distinct = [(i, j) for i in range(n) for j in range(n) if np.any(V[i] != V[j])]
        for _ in range(draw(st.integers(0, 2)) if distinct else 0):
            p1, p2 = draw(st.sampled_from(distinct))
            cyl.append({"p1": p1, "p2": p2, "radius": draw(st.floats(1e-3, 10)), "name": draw(names)})
        for _ in range(draw(st.integers(0, 2))):
            circ.append({"radius": draw(st.floats(1e-3, 10)), "center": draw(st.integers(0, n - 1)),
                         "p1": draw(st.integers(0, n - 1)), "p2": draw(st.integers(0, n - 1)), "name": draw(names)})
    return PolygonModel(V, faces, names=nm, lines=lines, cylinders=cyl, circles=circ)


def _same_loop(a: np.ndarray, b: np.ndarray) -> bool:
    """Equal up to a cyclic rotation (writers start each loop at a convex corner)."""
    if len(a) != len(b):
        return False
    return any(np.array_equal(np.roll(a, -k), b) for k in range(len(a)))


GARBAGE_TOKENS = [b"-1", b"1.5", b"nan", b"inf", b"-inf", b"1e308", b"-1e308", b"99999999999999999999", b"x",
                  b"\n", b"#", b"//", b" ", b",", b";", b"[", b"]", b"{", b"}", b'"', b"\xff\xfe", b"\x00", b"\xc3",
                  b"0", b"end_header\n", b"element face 3\n", b"load(\"x.cao\")\n", b"DATA binary\n", b"f 1 2 3\n"]


@st.composite
def mutations(draw, seed: bytes):
    """A valid file ``seed`` damaged by 1-4 random operations."""
    b = bytearray(seed)
    for _ in range(draw(st.integers(1, 4))):
        op = draw(st.sampled_from(["flip", "truncate", "insert", "insert_bytes", "delete", "duplicate"]))
        i = draw(st.integers(0, max(len(b) - 1, 0)))
        if op == "flip" and b:
            b[i] = draw(st.integers(0, 255))
        elif op == "truncate":
            del b[i:]
        elif op == "insert":
            b[i:i] = draw(st.sampled_from(GARBAGE_TOKENS))
        elif op == "insert_bytes":
            b[i:i] = draw(st.binary(min_size=1, max_size=12))
        elif op == "delete":
            del b[i:i + draw(st.integers(1, 16))]
        elif op == "duplicate":
            k = draw(st.integers(1, 40))
            b[i:i] = b[i:i + k]
    return bytes(b)


def _only_input_errors(reader, path: Path) -> None:
    """``reader(path)`` returns or raises InputError; no other exception, no RuntimeWarning."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        try:
            out = reader(path)
            if hasattr(out, "read_all"):
                out.read_all()
        except InputError:
            pass


# ====================================================================== valid seed files
def _seed_files() -> dict[str, bytes]:
    d = Path(tempfile.mkdtemp(prefix="mst-seeds-", dir=_TMP))
    out: dict[str, bytes] = {}
    m = gen.courtyard_model()  # faces with holes: bridged on write
    for suf in (".obj", ".wrl", ".cao"):
        save_model(d / f"m{suf}", m)
        out[f"model{suf}"] = (d / f"m{suf}").read_bytes()
    V, F = gen.gabled_house()
    for suf in (".obj", ".ply", ".stl", ".off"):
        save_triangles(d / f"t{suf}", V, F)
        out[f"tin{suf}"] = (d / f"t{suf}").read_bytes()
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\n"
            f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n")
    out["tin-ascii.ply"] = (head + "".join(f"{a} {b} {c}\n" for a, b, c in V)
                            + "".join(f"3 {a} {b} {c}\n" for a, b, c in F)).encode()
    stl = ["solid s"] + ["facet normal 0 0 1\nouter loop\n" + "".join(f"vertex {x} {y} {z}\n" for x, y, z in V[f])
                         + "endloop\nendfacet" for f in F[:6]] + ["endsolid s\n"]
    out["tin-ascii.stl"] = "\n".join(stl).encode()
    out["city.json"] = (
        b'{"type":"CityJSON","version":"1.1","transform":{"scale":[0.001,0.001,0.001],"translate":[0,0,0]},'
        b'"vertices":[[0,0,0],[1000,0,0],[1000,1000,0],[0,1000,0],[500,500,1000]],"CityObjects":{"b":{"type":'
        b'"Building","geometry":[{"type":"Solid","lod":"2","boundaries":[[[[0,3,2,1]],[[0,1,4]],[[1,2,4]],'
        b'[[2,3,4]],[[3,0,4]]]]}]}}}')
    out["visp.cao"] = (b'V1\n# ViSP style\n8 # points\n0 0 0 // a\n0 0 -0.08\n0.165 0 -0.08\n0.165 0 0\n'
                       b'0.165 0.068 0\n0.165 0.068 -0.08\n0 0.068 -0.08\n0 0.068 0\n3 # lines\n0 1\n1 2 name=l\n2 3\n'
                       b'0\n6\n4 0 1 2 3 name="front face" useLod=true\n4 1 6 5 2\n4 4 5 6 7\n4 0 3 4 7\n'
                       b'4 5 4 3 2\n4 0 7 6 1 // back\n1\n0 7 0.01 name=c\n1\n0.02 0 1 3\n')
    P = np.random.default_rng(0).normal(size=(40, 3)) * [10, 10, 2] + [1e5, 4e5, 10]
    for suf in (".ply", ".xyz", ".csv", ".las"):
        write_cloud(d / f"c{suf}", P)
        out[f"cloud{suf}"] = (d / f"c{suf}").read_bytes()
    body = "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in P)
    hdr = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 40\nHEIGHT 1\nPOINTS 40\n"
    out["cloud-ascii.pcd"] = (hdr + "DATA ascii\n" + body).encode()
    out["cloud-binary.pcd"] = (hdr + "DATA binary\n").encode() + (P - P.mean(0)).astype("<f4").tobytes()
    out["cloud-ascii.ply"] = (f"ply\nformat ascii 1.0\nelement vertex 40\nproperty double x\nproperty double y\n"
                              f"property double z\nend_header\n{body}").encode()
    return out


SEEDS = _seed_files()
MESH_READERS = {".obj": [load_model, load_triangles], ".wrl": [load_model, load_triangles],
                ".cao": [load_model, load_triangles], ".ply": [load_model, load_triangles],
                ".stl": [load_model, load_triangles], ".off": [load_model, load_triangles],
                ".json": [load_model, load_triangles]}
MESH_SEEDS = [k for k in SEEDS if not k.startswith("cloud")]
CLOUD_SEEDS = [k for k in SEEDS if k.startswith("cloud")]


def _suffix(name: str) -> str:
    return "." + name.rsplit(".", 1)[1]


# ====================================================================== robustness
@pytest.mark.parametrize("seed_name", MESH_SEEDS)
@settings(max_examples=30, **SETTINGS)
@given(data=st.data())
def test_mesh_readers_raise_only_input_errors(seed_name, data):
    blob = data.draw(mutations(SEEDS[seed_name]))
    suf = _suffix(seed_name)
    p = _tmpfile(f"x{suf}")
    p.write_bytes(blob)
    for reader in MESH_READERS[suf]:
        _only_input_errors(reader, p)


@pytest.mark.parametrize("seed_name", CLOUD_SEEDS)
@settings(max_examples=30, **SETTINGS)
@given(data=st.data())
def test_cloud_readers_raise_only_input_errors(seed_name, data):
    blob = data.draw(mutations(SEEDS[seed_name]))
    p = _tmpfile(f"x{_suffix(seed_name)}")
    p.write_bytes(blob)
    _only_input_errors(read_cloud, p)


def test_valid_seeds_read():
    """The seed files themselves are valid (so the mutations start from real files)."""
    for name, blob in SEEDS.items():
        p = _tmpfile(f"s{_suffix(name)}")
        p.write_bytes(blob)
        if name.startswith("cloud"):
            assert len(read_cloud(p)) == 40
        else:
            V, F = load_triangles(p)
            assert len(F) > 0 and np.isfinite(V).all()


# ====================================================================== round trips: models and meshes
@pytest.mark.parametrize("suffix", [".obj", ".wrl", ".cao"])
@settings(max_examples=25, **SETTINGS)
@given(model=polygon_models(with_primitives=True))
def test_polygon_model_round_trip(suffix, model):
    """save_model -> load_model: the same vertices (bit for bit), faces (up to where each loop
    starts), names, lines and ViSP primitives, as far as the format carries them."""
    p = _tmpfile(f"m{suffix}")
    save_model(p, model)
    back = load_model(p)
    np.testing.assert_array_equal(back.vertices, model.vertices)
    assert back.n_faces == model.n_faces
    assert all(_same_loop(a, b) for a, b in zip(back.faces, model.faces))
    if suffix == ".cao":
        assert back.names == model.names
        np.testing.assert_array_equal(back.lines, model.lines)
        assert back.cylinders == model.cylinders and back.circles == model.circles
    elif suffix == ".obj":
        # OBJ 'g a b' means two groups: a name is written as one token (blanks -> _)
        assert back.names == [None if n is None else re.sub(r"\s+", "_", n) for n in model.names]
        np.testing.assert_array_equal(back.lines, model.lines)
    # writing what was read gives the same bytes
    q = _tmpfile(f"again{suffix}")
    save_model(q, back)
    assert q.read_bytes() == p.read_bytes()


@st.composite
def triangle_meshes(draw):
    n = draw(st.integers(3, 30))
    V = np.array(draw(st.lists(st.tuples(coords, coords, coords), min_size=n, max_size=n)), np.float64)
    F = np.array(draw(st.lists(st.lists(st.integers(0, n - 1), min_size=3, max_size=3, unique=True),
                               min_size=1, max_size=20)), np.int64)
    return V, F


@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".off"])
@settings(max_examples=25, **SETTINGS)
@given(mesh=triangle_meshes())
def test_triangle_mesh_round_trip(suffix, mesh):
    """save_triangles -> load_triangles. OBJ (shortest round-trip decimals) and PLY (float64) are
    exact; STL stores float32 (budget: float32 rounding, 2^-24 relative); OFF is written by trimesh
    with its decimal precision (budget 1e-8 relative of the largest coordinate)."""
    V, F = mesh
    p = _tmpfile(f"t{suffix}")
    save_triangles(p, V, F)
    V2, F2 = load_triangles(p)
    if suffix in (".obj", ".ply"):
        np.testing.assert_array_equal(V2, V)
        np.testing.assert_array_equal(F2, F)
    elif suffix == ".stl":  # unwelded: 3 vertices per triangle
        np.testing.assert_array_equal(V2.reshape(-1, 3, 3), V[F].astype(np.float32).astype(np.float64))
    else:
        np.testing.assert_allclose(V2[F2], V[F], rtol=0, atol=1e-8 * max(1.0, np.abs(V).max()))


# ====================================================================== round trips: clouds
@st.composite
def clouds(draw):
    n = draw(st.integers(1, 50))
    off = np.array(draw(st.tuples(coords, coords, coords)))
    local = st.floats(-1e3, 1e3, allow_nan=False, width=64)
    P = np.array(draw(st.lists(st.tuples(local, local, local), min_size=n, max_size=n))) + off
    s = np.array(draw(st.lists(st.floats(-1e3, 1e3, width=32), min_size=n, max_size=n)), np.float32)
    return P, s


@pytest.mark.parametrize("suffix", [".ply", ".xyz", ".csv", ".txt", ".las"])
@settings(max_examples=20, **SETTINGS)
@given(cloud=clouds())
def test_cloud_round_trip(suffix, cloud):
    """write_cloud -> read_cloud. PLY float64 exact; text with 10 decimals (budget 5e-11 m plus the
    float64 ulp of the value); LAS with its 0.1 mm integer scale (budget half a step plus rounding)."""
    P, s = cloud
    p = _tmpfile(f"c{suffix}")
    write_cloud(p, P, {"d": s})
    Q = read_cloud(p)
    assert Q.shape == P.shape
    if suffix == ".ply":
        np.testing.assert_array_equal(Q, P)
    elif suffix == ".las":
        np.testing.assert_allclose(Q, P, rtol=0, atol=0.5e-4 + 1e-9 * np.abs(P).max())
    else:
        np.testing.assert_allclose(Q, P, rtol=0, atol=5e-11 + 4 * np.spacing(np.abs(P).max()))


@settings(max_examples=20, **SETTINGS)
@given(cloud=clouds())
def test_cloud_round_trip_float32(cloud):
    """A float32 PLY keeps float32 coordinates: what comes back is the float32 rounding, exactly."""
    P, _ = cloud
    p = _tmpfile("c32.ply")
    write_cloud(p, P, xyz_dtype=np.float32)
    np.testing.assert_array_equal(read_cloud(p), P.astype(np.float32).astype(np.float64))


# ====================================================================== poses and trajectories (readers owned by
# core/trajectory.py and core/poses.py: tested here, not changed)


@st.composite
def poses(draw, n_min=1, n_max=20):
    n = draw(st.integers(n_min, n_max))
    w = np.array(draw(st.lists(st.tuples(*[st.floats(-3, 3)] * 3), min_size=n, max_size=n)))
    t = np.array(draw(st.lists(st.tuples(*[st.floats(-1e4, 1e4)] * 3), min_size=n, max_size=n)))
    T = np.stack([make_T(so3_exp(wi), ti) for wi, ti in zip(w, t)])
    times = np.cumsum(np.array(draw(st.lists(st.floats(1e-3, 10), min_size=n, max_size=n))))
    return times, T


def _assert_poses_close(A, B, t_scale):
    # budget: TUM text has 9 decimals (5e-10) per value; a unit quaternion rounded that way moves
    # the rotation by ~1e-9 rad, i.e. ~1e-9 * |t| in the derived matrices
    np.testing.assert_allclose(A[:, :3, :3], B[:, :3, :3], atol=1e-8)
    np.testing.assert_allclose(A[:, :3, 3], B[:, :3, 3], atol=1e-9 + 1e-8 * t_scale)


@settings(max_examples=25, **SETTINGS)
@given(traj=poses())
def test_tum_round_trip(traj):
    times, T = traj
    p = _tmpfile("traj.txt")
    write_tum(p, times, T, header="mst test")
    t2, T2 = read_tum(p)
    np.testing.assert_allclose(t2, times, atol=5e-7)  # 6 decimals
    _assert_poses_close(T2, T, np.abs(T[:, :3, 3]).max())
    tr = read_trajectory(p)
    assert tr.has_rotation and np.array_equal(tr.t, t2) and np.array_equal(tr.T_model_cam, T2)


@settings(max_examples=25, **SETTINGS)
@given(traj=poses(1, 1))
def test_pose_file_round_trip(traj):
    _, T = traj
    T_cam_model = inv_T(T[0])
    p = _tmpfile("pose0.txt")
    write_pose_file(p, T_cam_model)
    _assert_poses_close(read_pose_file(p)[None], T_cam_model[None], np.abs(T_cam_model[:3, 3]).max())


@settings(max_examples=25, **SETTINGS)
@given(traj=poses(1, 1), rows=st.sampled_from([3, 4]))
def test_rigid_transform_round_trip(traj, rows):
    """A 4x4/3x4 matrix written with repr (shortest round-trip) reads back within one SVD
    re-orthonormalisation (a few ulp)."""
    T = traj[1][0]
    p = _tmpfile("M.txt")
    p.write_text("# depth_M_color\n" + "\n".join(" ".join(repr(float(v)) for v in r) for r in T[:rows]) + "\n")
    np.testing.assert_allclose(read_rigid_transform(p), T, atol=1e-12 * max(1.0, np.abs(T).max()))


@settings(max_examples=20, **SETTINGS)
@given(traj=poses(2, 10))
def test_kitti_and_csv_round_trip(traj):
    times, T = traj
    k = _tmpfile("poses.kitti")
    k.write_text("".join(" ".join(repr(float(v)) for v in Ti[:3].ravel()) + "\n" for Ti in T))
    Tk = read_trajectory(k, fmt="kitti").T_model_cam
    np.testing.assert_allclose(Tk, T, atol=1e-12 * max(1.0, np.abs(T).max()))
    c = _tmpfile("gps.csv")
    c.write_text("time,e,n,h\n" + "".join(",".join(repr(float(v)) for v in (ti, *xyz)) + "\n" for ti, xyz in zip(times, T[:, :3, 3])))
    tr = read_trajectory(c, csv_columns="t=time,x=e,y=n,z=h")
    tc, Tc = tr.t, tr.T_model_cam
    assert not tr.has_rotation
    np.testing.assert_array_equal(tc, times)
    np.testing.assert_array_equal(Tc[:, :3, 3], T[:, :3, 3])


def _pose_seeds() -> dict[str, tuple[bytes, object]]:
    times = np.arange(5) / 30.0
    T = np.stack([make_T(so3_exp(np.array([0.1 * i, -0.2, 0.3])), np.array([i, 2.0, -1.0])) for i in range(5)])
    d = Path(tempfile.mkdtemp(prefix="mst-pose-seeds-", dir=_TMP))
    write_tum(d / "t.txt", times, T, header="seed")
    write_pose_file(d / "p.txt", inv_T(T[0]))
    M = "\n".join(" ".join(f"{v:.9f}" for v in r) for r in T[1]) + "\n"
    kitti = "".join(" ".join(f"{v:.9f}" for v in Ti[:3].ravel()) + "\n" for Ti in T)
    csv = "t,x,y,z,qx,qy,qz,qw\n" + "".join(f"{i / 30:.4f},{i},2,-1,0,0,0,1\n" for i in range(5))
    return {"tum": ((d / "t.txt").read_bytes(), read_tum),
            "pose": ((d / "p.txt").read_bytes(), read_pose_file),
            "matrix": (M.encode(), read_rigid_transform),
            "kitti": (kitti.encode(), lambda p: read_trajectory(p, fmt="kitti")),
            "csv": (csv.encode(), lambda p: read_trajectory(p, fmt="csv"))}


POSE_SEEDS = _pose_seeds()


@pytest.mark.parametrize("kind", sorted(POSE_SEEDS))
@settings(max_examples=30, **SETTINGS)
@given(data=st.data())
def test_pose_readers_raise_only_input_errors_ascii(kind, data):
    """Mutations that keep the file ASCII (the readers' own parsing)."""
    seed, reader = POSE_SEEDS[kind]
    blob = data.draw(mutations(seed))
    blob = bytes(b & 0x7F for b in blob)
    p = _tmpfile(f"x.{'csv' if kind == 'csv' else 'txt'}")
    p.write_bytes(blob)
    _only_input_errors(reader, p)


@pytest.mark.parametrize("kind", sorted(POSE_SEEDS))
def test_pose_readers_non_utf8(kind):
    seed, reader = POSE_SEEDS[kind]
    p = _tmpfile(f"x.{'csv' if kind == 'csv' else 'txt'}")
    p.write_bytes(seed[:10] + b"\xff\xfe\xc3" + seed[10:])
    _only_input_errors(reader, p)
