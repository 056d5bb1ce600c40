"""Frame sources: a video file, a folder of images, a glob or a printf pattern.

``open_frames(spec, frames="a:b:step", scale=1.0, fps=None)`` returns a :class:`FrameSource`
that yields ``(index, time_s, bgr)`` where ``index`` is the frame number in the source (0-based),
``time_s`` is ``index / fps`` for videos (the video's fps unless ``fps`` is given) and ``index``
for image sequences unless ``fps`` is given (then ``index / fps``), and ``bgr`` is an 8-bit
(H, W, 3) image already resized by ``scale``.

Spec forms: ``video.mp4`` (anything OpenCV's FFMPEG backend opens), ``rgb/`` (a folder: every
.png/.jpg/.jpeg/.bmp/.tif/.tiff file, sorted by name), ``"rgb/*.png"`` (a glob, sorted),
``rgb/%06d.png`` (a printf pattern, numbered from 0 or the first existing number).
"""

from __future__ import annotations

import glob as _glob
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mst import ConfigError, InputError
from mst.pipeline.depth_io import IMAGE_SUFFIXES as IMAGE_EXTS
from mst.pipeline.depth_io import natural_key

# FFmpeg prints its own errors ("moov atom not found") on stderr; mst reports one clean line instead
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")



#: the sides a (scaled) frame may have, pixels: 0 px cannot be resized to, above 16384 one frame
#: takes gigabytes (the --scale of a typo, 1000 instead of 1)
MIN_SIDE_PX = 1
MAX_SIDE_PX = 16384


def parse_range(text: str | None) -> tuple[int, int | None, int]:
    """``"a:b:step"`` (each part optional, b exclusive) -> ``(start, stop or None, step)``."""
    if text is None or text == "":
        return 0, None, 1
    parts = text.split(":")
    if len(parts) > 3:
        raise ConfigError("frames", f"{text!r}: expected a:b:step")
    try:
        vals = [int(p) if p.strip() else None for p in parts] + [None] * (3 - len(parts))
    except ValueError:
        raise ConfigError("frames", f"{text!r}: not integers") from None
    a, b, s = vals
    if len(parts) == 1 and a is not None:  # "a" alone: from a to the end
        b = None
    a = a or 0
    s = 1 if s is None else s  # an empty step is 1; a step of 0 is an error, not 1
    if a < 0 or s <= 0 or (b is not None and b <= a):
        raise ConfigError("frames", f"{text!r}: need 0 <= a < b and step > 0")
    return a, b, s


@dataclass
class FrameSource:
    """An opened frame source (see module docstring). ``width``/``height`` are after scaling."""

    spec: str
    kind: str  # "video" | "images"
    indices: list[int]
    fps: float | None
    scale: float
    width: int
    height: int
    files: list[Path] | None = None
    src_width: int = 0
    src_height: int = 0

    def __len__(self) -> int:
        return len(self.indices)

    def time_of(self, index: int) -> float:
        """Time stamp (seconds, or the index for image sequences without fps)."""
        return index / self.fps if self.fps else float(index)

    def _resize(self, img: np.ndarray) -> np.ndarray:
        import cv2

        if img.ndim == 2:
            img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
        elif img.shape[2] == 4:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
        if img.dtype != np.uint8:
            img = cv2.convertScaleAbs(img, alpha=255.0 / max(1.0, float(img.max())))
        if self.scale != 1.0:
            img = cv2.resize(img, (self.width, self.height), interpolation=cv2.INTER_AREA)
        return img

    def __iter__(self) -> Iterator[tuple[int, float, np.ndarray]]:
        import cv2

        if self.kind == "images":
            for i in self.indices:
                f = self.files[i]
                img = cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
                if img is None:
                    raise InputError(f, "image could not be read")
                if img.shape[:2] != (self.src_height, self.src_width):
                    raise InputError(f, f"image size {img.shape[1]}x{img.shape[0]} differs from the first frame's "
                                        f"{self.src_width}x{self.src_height}")
                yield i, self.time_of(i), self._resize(img)
            return
        cap = cv2.VideoCapture(self.spec)
        try:
            want = set(self.indices)
            last = self.indices[-1] if self.indices else -1
            k = 0
            if self.indices and self.indices[0] > 0:
                cap.set(cv2.CAP_PROP_POS_FRAMES, self.indices[0])
                k = self.indices[0]
            while k <= last:
                ok, img = cap.read()
                if not ok:
                    break
                if k in want:
                    yield k, self.time_of(k), self._resize(img)
                k += 1
        finally:
            cap.release()


def prefetched(frames, depth: int = 3) -> Iterator:
    """Iterate ``frames`` (any iterable, e.g. a :class:`FrameSource`) with its items produced ahead in a
    background thread, at most ``depth`` of them waiting: a video's decoding (OpenCV releases the GIL while it
    reads) overlaps the caller's work on the previous frame. The same items in the same order; an exception
    raised while producing one is raised here at that item; stopping early (``break``, an exception in the
    caller) stops the thread and releases the source."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=max(1, int(depth)))
    stop = threading.Event()
    done = object()

    def put(item) -> bool:
        while not stop.is_set():
            try:
                q.put(item, timeout=0.05)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        it = iter(frames)
        try:
            for item in it:
                if not put((item, None)):
                    break
            else:
                put((done, None))
        except BaseException as e:  # handed to the consumer, raised there
            put((done, e))
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()  # a generator's finally (the video capture's release) runs in this thread

    th = threading.Thread(target=produce, name="mst-frames", daemon=True)
    th.start()
    try:
        while True:
            item, err = q.get()
            if item is done:
                if err is not None:
                    raise err
                return
            yield item
    finally:
        stop.set()
        th.join()


def _printf_files(spec: str) -> list[Path]:
    files = []
    k0 = 0
    if not os.path.exists(spec % 0):
        k0 = 1
    k = k0
    while os.path.exists(spec % k):
        files.append(Path(spec % k))
        k += 1
    return files


def open_frames(spec: str | os.PathLike, frames: str | None = None, scale: float = 1.0,
                fps: float | None = None) -> FrameSource:
    """Open a frame source; raise :class:`mst.InputError` when it cannot be read.

    The first frame is decoded here so that an unreadable video fails before any work starts.
    """
    import cv2

    spec = str(spec)
    if not scale > 0:
        raise ConfigError("scale", f"must be > 0, got {scale}")
    a, b, s = parse_range(frames)
    p = Path(spec)
    files: list[Path] | None = None
    if p.is_dir():
        # natural order (img2 before img10), the same order `mst fuse` pairs depth/colour frames in
        files = sorted((f for f in p.iterdir() if f.suffix.lower() in IMAGE_EXTS and not f.name.startswith(".")), key=natural_key)
        if not files:
            raise InputError(p, "folder holds no images (.png .jpg .bmp .tif)")
    elif re.search(r"%0?\d*d", spec):
        files = _printf_files(spec)
        if not files:
            raise InputError(spec, "no file matches the printf pattern")
    elif any(c in spec for c in "*?["):
        files = sorted((Path(f) for f in _glob.glob(spec)), key=natural_key)
        if not files:
            raise InputError(spec, "no file matches the glob")
    elif p.is_file() and p.suffix.lower() in IMAGE_EXTS:
        files = [p]
    elif not p.exists():
        raise InputError(p, "frames source does not exist")

    if files is not None:
        first = cv2.imread(str(files[0]), cv2.IMREAD_UNCHANGED)
        if first is None:
            raise InputError(files[0], "image could not be read")
        h, w = first.shape[:2]
        n = len(files)
        kind = "images"
        src_fps = fps
    else:
        cap = cv2.VideoCapture(spec)
        ok, first = cap.read() if cap.isOpened() else (False, None)
        if not ok or first is None:
            cap.release()
            raise InputError(p, "video could not be decoded (not a video, or a codec OpenCV lacks)")
        h, w = first.shape[:2]
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        vfps = cap.get(cv2.CAP_PROP_FPS)
        cap.release()
        if n <= 0:
            n = 10**6  # unknown length: read until the stream ends
        kind = "video"
        src_fps = fps or (vfps if vfps and vfps > 0 else 30.0)
    stop = n if b is None else min(b, n)
    indices = list(range(a, stop, s))
    if not indices:
        raise ConfigError("frames", f"{frames!r} selects no frame of the {n} in {spec}")
    W, H = int(round(w * scale)), int(round(h * scale))
    if min(W, H) < MIN_SIDE_PX or max(W, H) > MAX_SIDE_PX:
        raise ConfigError("scale", f"{scale:g} turns the {w}x{h} frames into {W}x{H}: a side must stay within "
                                    f"{MIN_SIDE_PX}..{MAX_SIDE_PX} px")
    return FrameSource(spec, kind, indices, src_fps, float(scale), W, H, files, w, h)


def check_camera_size(src: FrameSource, cam, camera_path: str | os.PathLike):
    """Return the camera for the (scaled) frames; raise when the camera's stated size differs.

    A camera without a size (ViSP tracker XML) takes the source's size. A camera with a size must
    match the unscaled frames; it is then scaled by ``src.scale``.
    """
    if cam.width and cam.height and (cam.width, cam.height) != (src.src_width, src.src_height):
        raise InputError(camera_path, f"camera is for {cam.width}x{cam.height} images but the frames are "
                                      f"{src.src_width}x{src.src_height}")
    cam = cam.with_size(src.src_width, src.src_height)
    return cam.scaled(src.scale) if src.scale != 1.0 else cam
