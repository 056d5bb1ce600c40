"""Pinhole cameras: intrinsics, distortion, projection, and camera files.

Frames: the camera frame is x right, y down, z forward (OpenCV/ViSP); pixel (0, 0) is the centre of
the top-left pixel. Units: pixels for intrinsics, metres for 3D points.

Camera files read by :func:`read_camera` (detected by content):

* ViSP tracker XML ``<conf><camera><u0/><v0/><px/><py/></camera></conf>`` (no size: the size comes
  from the video or ``width``/``height`` given by the caller);
* ViSP camera XML ``<root><camera><name/><image_width/><image_height/><model><type/><px/>...``
  (``perspectiveProjWithoutDistortion`` or ``perspectiveProjWithDistortion`` with ``kud``/``kdu``;
  ViSP's single radial term is mapped onto OpenCV's ``k1``, an approximation stated in the docs);
* OpenCV YAML/JSON (``camera_matrix``, ``distortion_coefficients``, ``image_width``/``image_height``)
  as written by OpenCV's calibration sample, and the mst JSON file written by :func:`write_camera`
  (``{"width", "height", "fx", "fy", "cx", "cy", "dist": [k1, k2, p1, p2, k3]}``).
"""

from __future__ import annotations

import json
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from mst import InputError

#: bounds of plausible intrinsics: a focal length of 1e7 px is a 1000x telescope on a 10k-px sensor;
#: image sides beyond 1e6 px do not exist; |distortion coefficients| beyond 1e4 overflow the model
MAX_FOCAL_PX = 1e7
MAX_SIZE_PX = 1_000_000
MAX_DIST_COEFF = 1e4


@dataclass
class Camera:
    """Pinhole camera with optional OpenCV distortion ``dist = (k1, k2, p1, p2[, k3...])``.

    ``width``/``height`` are in pixels and may be 0 when the file does not state them.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int = 0
    height: int = 0
    dist: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self) -> None:
        """Refuse intrinsics no camera has (ValueError; :func:`read_camera` names the file)."""
        self.dist = np.asarray(self.dist, dtype=np.float64).ravel()
        vals = np.array([self.fx, self.fy, self.cx, self.cy], dtype=float)
        if not np.isfinite(vals).all() or self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"invalid intrinsics fx={self.fx} fy={self.fy} cx={self.cx} cy={self.cy}")
        if max(self.fx, self.fy) > MAX_FOCAL_PX or np.abs(vals[2:]).max() > MAX_FOCAL_PX:
            raise ValueError(f"intrinsics beyond {MAX_FOCAL_PX:g} px: fx={self.fx:g} fy={self.fy:g} cx={self.cx:g} "
                             f"cy={self.cy:g}")
        if not (0 <= int(self.width) <= MAX_SIZE_PX and 0 <= int(self.height) <= MAX_SIZE_PX):
            raise ValueError(f"invalid image size {self.width:.6g}x{self.height:.6g}")
        if len(self.dist) and not np.isfinite(self.dist).all():
            raise ValueError(f"distortion coefficients hold NaN or inf: {self.dist.tolist()}")
        if len(self.dist) and np.abs(self.dist).max() > MAX_DIST_COEFF:
            raise ValueError(f"distortion coefficient beyond {MAX_DIST_COEFF:g}: {self.dist.tolist()}")

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix (pixels)."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def has_distortion(self) -> bool:
        return bool(len(self.dist)) and bool(np.any(self.dist != 0))

    def with_size(self, width: int, height: int) -> Camera:
        return replace(self, width=int(width), height=int(height))

    def scaled(self, s: float) -> Camera:
        """The camera for images resized by factor ``s`` (pixel-centre convention kept)."""
        return Camera(self.fx * s, self.fy * s, (self.cx + 0.5) * s - 0.5, (self.cy + 0.5) * s - 0.5,
                      int(round(self.width * s)), int(round(self.height * s)), self.dist.copy())

    def project(self, X_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points (z > 0) -> (N, 2) pixels, distortion applied."""
        X = np.asarray(X_cam, dtype=np.float64)
        x = X[:, 0] / X[:, 2]
        y = X[:, 1] / X[:, 2]
        if self.has_distortion:
            x, y = self._distort(x, y)
        return np.stack([self.fx * x + self.cx, self.fy * y + self.cy], axis=1)

    def _distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        d = np.zeros(5)
        d[: min(5, len(self.dist))] = self.dist[:5]
        k1, k2, p1, p2, k3 = d
        r2 = x * x + y * y
        rad = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        return (x * rad + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * rad + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)

    def unproject(self, uv: np.ndarray) -> np.ndarray:
        """(N, 2) pixels -> (N, 2) normalised image coordinates (distortion removed)."""
        uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
        if self.has_distortion:
            import cv2

            return cv2.undistortPoints(uv.reshape(-1, 1, 2), self.K, self.dist).reshape(-1, 2)
        return np.stack([(uv[:, 0] - self.cx) / self.fx, (uv[:, 1] - self.cy) / self.fy], axis=1)

    def to_dict(self) -> dict:
        return {"width": self.width, "height": self.height, "fx": self.fx, "fy": self.fy,
                "cx": self.cx, "cy": self.cy, "dist": self.dist.tolist()}


def write_camera(path: str | os.PathLike, cam: Camera) -> None:
    """Write the mst JSON camera file."""
    Path(path).write_text(json.dumps({"model": "pinhole", **cam.to_dict()}, indent=2) + "\n")


def _xml_float(node: ET.Element, tag: str, path: Path) -> float:
    el = node.find(tag)
    if el is None or el.text is None:
        raise InputError(path, f"camera XML has no <{tag}>")
    try:
        return float(el.text)
    except ValueError:
        raise InputError(path, f"<{tag}> is not a number: {el.text!r}") from None


def _read_visp_xml(path: Path) -> Camera:
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as e:
        raise InputError(path, f"not valid XML ({e})") from None
    cam = root if root.tag == "camera" else root.find("camera")
    if cam is None:
        raise InputError(path, "no <camera> element")
    model = cam.find("model")
    w = int(float(cam.findtext("image_width", "0") or 0))
    h = int(float(cam.findtext("image_height", "0") or 0))
    if model is not None:  # <root><camera><model> layout (vpXmlParserCamera)
        # prefer the model without distortion when several are given
        models = cam.findall("model")
        chosen = next((m for m in models if (m.findtext("type") or "").strip() == "perspectiveProjWithoutDistortion"), models[0])
        px, py = _xml_float(chosen, "px", path), _xml_float(chosen, "py", path)
        u0, v0 = _xml_float(chosen, "u0", path), _xml_float(chosen, "v0", path)
        dist = []
        if chosen.find("kud") is not None and (chosen.findtext("type") or "").strip() == "perspectiveProjWithDistortion":
            # ViSP: u_d = u0 + px*x*(1 + kud*r^2); OpenCV k1 plays that role (first-order match)
            dist = [_xml_float(chosen, "kud", path), 0.0, 0.0, 0.0]
        return Camera(px, py, u0, v0, w, h, np.asarray(dist, float))
    # tracker <conf><camera> layout
    return Camera(_xml_float(cam, "px", path), _xml_float(cam, "py", path),
                  _xml_float(cam, "u0", path), _xml_float(cam, "v0", path), w, h)


def _opencv_matrix(node) -> np.ndarray:
    if isinstance(node, dict) and "data" in node:
        return np.asarray(node["data"], dtype=np.float64).reshape(int(node.get("rows", -1)), -1)
    return np.asarray(node, dtype=np.float64)


def _camera_from_mapping(d: dict, path: Path) -> Camera:
    if "fx" in d:
        return Camera(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                      int(d.get("width", 0)), int(d.get("height", 0)), np.asarray(d.get("dist", []), float))
    km = d.get("camera_matrix", d.get("K", d.get("cameraMatrix")))
    if km is None:
        raise InputError(path, "no camera_matrix / fx in the camera file")
    K = _opencv_matrix(km).reshape(3, 3)
    dist = d.get("distortion_coefficients", d.get("dist_coeffs", d.get("D", [])))
    return Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], int(d.get("image_width", d.get("width", 0))),
                  int(d.get("image_height", d.get("height", 0))), _opencv_matrix(dist).ravel() if len(np.atleast_1d(dist)) else np.zeros(0))


def _read_opencv_yaml(path: Path) -> Camera:
    import cv2

    try:  # OpenCV's parser raises cv2.error, or SystemError from its bindings, on malformed YAML
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError):
        raise InputError(path, "OpenCV could not parse the YAML camera file (malformed YAML)") from None
    if not fs.isOpened():
        raise InputError(path, "OpenCV could not parse the YAML camera file")
    try:
        K = fs.getNode("camera_matrix").mat()
        if K is None:
            raise InputError(path, "no camera_matrix in the YAML camera file")
        if K.shape != (3, 3):
            raise InputError(path, f"camera_matrix is {K.shape[0]}x{K.shape[1] if K.ndim > 1 else 1}, expected 3x3")
        D = fs.getNode("distortion_coefficients").mat()
        w = fs.getNode("image_width")
        h = fs.getNode("image_height")
        return Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], int(w.real()) if not w.empty() else 0,
                      int(h.real()) if not h.empty() else 0, np.zeros(0) if D is None else D.ravel())
    except (cv2.error, SystemError) as e:
        raise InputError(path, f"bad YAML camera file ({str(e).strip().splitlines()[-1][:120]})") from None
    finally:
        fs.release()


def read_camera(path: str | os.PathLike) -> Camera:
    """Read a camera file (ViSP XML, OpenCV YAML/JSON, or mst JSON), format detected by content."""
    from mst import read_text, require_file

    p = require_file(path, "camera file")
    text = p.read_bytes().decode("utf-8-sig", errors="replace").lstrip()
    try:
        if text.startswith("<"):
            return _read_visp_xml(p)
        if text.startswith("{"):
            try:
                d = json.loads(text)
            except json.JSONDecodeError as e:
                raise InputError(p, f"not valid JSON ({e.msg}, line {e.lineno})") from None
            read_text(p, "camera file")  # JSON is UTF-8: a stray byte is an error, not a replacement character
            if not isinstance(d, dict):
                raise InputError(p, "camera JSON must be an object with fx fy cx cy (or camera_matrix)")
            return _camera_from_mapping(d, p)
        if text.startswith("%YAML") or "camera_matrix" in text:
            return _read_opencv_yaml(p)
    except (ValueError, KeyError, TypeError) as e:
        raise InputError(p, f"bad camera parameters ({e})") from None
    raise InputError(p, "unknown camera format (expected ViSP XML, OpenCV YAML/JSON or mst JSON)")
