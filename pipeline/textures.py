"""Procedural, tileable textures for the synthetic renderer, and their filtered lookup.

Each texture is generated once per scene from a seed (value noise summed over octaves, bricks,
tiles, terrain) as a tileable ``uint8`` RGB image of ``size x size`` texels, then stored with a
box-filtered mip pyramid. :meth:`Texture.sample` looks up colours at 3D hit points mapped to the
texture plane with mip-mapping (level chosen from the pixel footprint), which
anti-aliases mortar lines and high-frequency noise, so texture edges need no extra rays.

Units: ``texel_m`` is the world size of one level-0 texel in metres; lookups take texel
coordinates (level 0); colours are float32 in [0, 1], RGB order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


# ---------------------------------------------------------------------------- generation helpers
def _resize_wrap(grid: np.ndarray, size: int) -> np.ndarray:
    """Bicubic upsampling of a periodic ``(c, c[, k])`` grid to ``(size, size[, k])``, keeping it tileable.

    Coarse grids are first upsampled to at most 32 texels per cell (bicubic, with a wrapped border),
    then bilinearly to ``size``: the result is smooth at those scales either way.
    """
    import cv2

    c = grid.shape[0]
    inter = min(size, c * 32)
    scale = inter // c
    pad = 2
    g = np.pad(grid, ((pad, pad), (pad, pad)) + ((0, 0),) * (grid.ndim - 2), mode="wrap").astype(np.float32)
    big = cv2.resize(g, ((c + 2 * pad) * scale, (c + 2 * pad) * scale), interpolation=cv2.INTER_CUBIC)
    if inter == size:
        return big[pad * scale: pad * scale + size, pad * scale: pad * scale + size]
    # keep one wrapped intermediate texel on each side, then bilinear to the final size
    k = size // inter
    sub = big[pad * scale - 1: pad * scale + inter + 1, pad * scale - 1: pad * scale + inter + 1]
    up = cv2.resize(sub, ((inter + 2) * k, (inter + 2) * k), interpolation=cv2.INTER_LINEAR)
    return up[k: k + size, k: k + size]


def value_noise(size: int, cells: int, rng: np.random.Generator, channels: int = 0) -> np.ndarray:
    """Tileable value noise: uniform random values on a ``cells x cells`` lattice, bicubic-interpolated.

    Returns float32 ``(size, size)`` (or ``(size, size, channels)``), roughly in [0, 1]. ``cells`` is
    rounded to a power of two (``size`` is one).
    """
    cells = int(min(2 ** round(math.log2(max(cells, 1))), size))  # power of two: divides size
    shape = (cells, cells) if not channels else (cells, cells, channels)
    return _resize_wrap(rng.random(shape, dtype=np.float32), size)


def fbm(size: int, base_cells: int, octaves: int, rng: np.random.Generator, persistence: float = 0.5) -> np.ndarray:
    """Multi-octave (fractal) value noise, tileable, normalised to mean 0.5 and range about [0, 1].

    Octave ``o`` has ``base_cells * 2**o`` lattice cells over the tile and amplitude ``persistence**o``.
    """
    acc = np.zeros((size, size), np.float32)
    amp, tot = 1.0, 0.0
    for o in range(octaves):
        cells = base_cells * 2**o
        if cells > size:
            break
        acc += amp * (value_noise(size, cells, rng) - 0.5)
        tot += amp
        amp *= persistence
    acc /= max(tot, 1e-6)
    return np.clip(0.5 + 1.6 * acc, 0.0, 1.0)


def _speckle(size: int, rng: np.random.Generator, density: float, strength: float) -> np.ndarray:
    """Sparse dark/bright dots (1-3 texels), good corners for KLT/ORB; multiplicative factor around 1."""
    import cv2

    dots = (rng.random((size, size), dtype=np.float32) < density).astype(np.float32)
    sign = np.where(rng.random((size, size), dtype=np.float32) < 0.5, -1.0, 1.0).astype(np.float32)
    pad = 4
    d = np.pad(dots * sign, pad, mode="wrap")
    d = cv2.GaussianBlur(d, (0, 0), 0.8)[pad:-pad, pad:-pad] * 3.0
    return 1.0 + strength * np.clip(d, -1, 1)


def brick_texture(size: int, rng: np.random.Generator, rows: int = 32, bricks_per_row: int = 8) -> np.ndarray:
    """Running-bond brick wall: per-brick colour, mortar lines, grain noise. float32 (size, size, 3)."""
    h = size // rows
    w = size // bricks_per_row
    y = np.arange(size, dtype=np.float32)
    x = np.arange(size, dtype=np.float32)
    row = (y // h).astype(np.int64)                      # (size,) brick row of each texel row
    by = y - row * h
    dy = np.minimum(by, h - by)                          # distance to the horizontal mortar lines
    par = (row % 2).astype(np.int64)
    xo = x[None, :] + np.array([[0.0], [w / 2.0]], np.float32)   # (2, size): even / odd rows
    col2 = (xo // w).astype(np.int64) % bricks_per_row
    bx = xo - np.floor(xo / w) * w
    dx2 = np.minimum(bx, w - bx)
    dist = np.minimum(dx2[par], dy[:, None])             # (size, size)
    mortar_w = max(1.5, 0.12 * h)
    mortar = np.clip((mortar_w - dist) + 0.5, 0.0, 1.0)[..., None]  # 1 in the mortar, soft over 1 texel
    tone = rng.random((rows, bricks_per_row), dtype=np.float32)
    hue = rng.random((rows, bricks_per_row), dtype=np.float32)[..., None]
    c0 = np.array([0.62, 0.30, 0.22], np.float32)
    c1 = np.array([0.55, 0.42, 0.30], np.float32)
    brick_col = (c0 * (1 - hue) + c1 * hue) * (0.6 + 0.7 * tone)[..., None]   # (rows, bricks, 3)
    img = brick_col[row[:, None], col2[par]]            # (size, size, 3)
    grain = fbm(size, 16, 6, rng, 0.6)[..., None]
    img *= 0.65 + 0.7 * grain
    mortar_col = np.array([0.78, 0.76, 0.72], np.float32) * (0.8 + 0.4 * fbm(size, 64, 3, rng)[..., None])
    img += (mortar_col - img) * mortar
    img *= _speckle(size, rng, 0.004, 0.35)[..., None]
    return img


def tile_texture(size: int, rng: np.random.Generator, tiles: int = 8) -> np.ndarray:
    """Floor tiles: per-tile colour, grout lines, marble-like veins and speckles. float32 (size, size, 3)."""
    s = size // tiles
    y, x = np.mgrid[0:size, 0:size].astype(np.float32)
    ti, tj = (y // s).astype(np.int64), (x // s).astype(np.int64)
    lx, ly = x - tj * s, y - ti * s
    dist = np.minimum(np.minimum(lx, s - lx), np.minimum(ly, s - ly))
    grout = np.clip((max(2.0, 0.03 * s) - dist) + 0.5, 0.0, 1.0)
    tone = rng.random((tiles, tiles), dtype=np.float32)[ti, tj][..., None]
    palette = np.array([[0.80, 0.78, 0.72], [0.55, 0.58, 0.62], [0.70, 0.62, 0.50]], np.float32)
    pick = rng.integers(0, len(palette), (tiles, tiles))[ti, tj]
    veins = fbm(size, 8, 7, rng, 0.55)
    veins = np.abs(np.sin(veins * 18.0))[..., None]
    col = palette[pick] * (0.7 + 0.35 * tone) * (0.75 + 0.25 * veins)
    col = col * (0.8 + 0.4 * fbm(size, 32, 5, rng)[..., None])
    img = col * (1 - grout[..., None]) + np.float32(0.25) * grout[..., None]
    return img * _speckle(size, rng, 0.006, 0.45)[..., None]


def terrain_texture(size: int, rng: np.random.Generator) -> np.ndarray:
    """Aerial ground: grass, soil and paved patches with fine detail. float32 (size, size, 3)."""
    m = fbm(size, 4, 6, rng, 0.55)
    m2 = fbm(size, 8, 5, rng, 0.5)
    grass = np.array([0.30, 0.45, 0.20], np.float32)
    soil = np.array([0.50, 0.40, 0.28], np.float32)
    paved = np.array([0.52, 0.52, 0.50], np.float32)
    wg = np.clip((m - 0.45) * 6, 0, 1)[..., None]
    wp = np.clip((m2 - 0.62) * 8, 0, 1)[..., None]
    col = soil * (1 - wg) + grass * wg
    col = col * (1 - wp) + paved * wp
    col = col * (0.55 + 0.9 * fbm(size, 64, 5, rng, 0.6)[..., None])
    return col * _speckle(size, rng, 0.01, 0.5)[..., None]


def plaster_texture(size: int, rng: np.random.Generator) -> np.ndarray:
    """Light plaster/concrete with stains and speckles. float32 (size, size, 3)."""
    n = fbm(size, 8, 8, rng, 0.6)[..., None]
    stains = fbm(size, 3, 3, rng)[..., None]
    col = np.array([0.78, 0.77, 0.74], np.float32) * (0.6 + 0.55 * n) * (0.8 + 0.35 * stains)
    return col * _speckle(size, rng, 0.008, 0.5)[..., None]


def concrete_texture(size: int, rng: np.random.Generator) -> np.ndarray:
    """Mid-grey concrete floor: multi-octave blotches, fine grain and speckles, no long straight lines
    (KLT/ORB find corners, a model's silhouette against it stays clean). float32 (size, size, 3)."""
    n = fbm(size, 16, 7, rng, 0.65)[..., None]
    blot = fbm(size, 4, 3, rng)[..., None]
    col = np.array([0.50, 0.49, 0.47], np.float32) * (0.55 + 0.8 * n) * (0.75 + 0.45 * blot)
    return col * _speckle(size, rng, 0.012, 0.6)[..., None]


def modulation_texture(size: int, rng: np.random.Generator) -> np.ndarray:
    """Low-frequency brightness modulation (mean 1), applied at a different scale and rotation
    to break the periodicity of the tiled textures. float32 (size, size, 3)."""
    m = fbm(size, 4, 4, rng, 0.5)
    return np.repeat((0.7 + 0.6 * m)[..., None], 3, axis=2)


GENERATORS = {
    "brick": brick_texture,
    "tiles": tile_texture,
    "terrain": terrain_texture,
    "plaster": plaster_texture,
    "concrete": concrete_texture,
    "modulation": modulation_texture,
}


#: fixed random-stream number per texture kind (adding a kind never changes the others)
_STREAM = {"brick": 0, "modulation": 1, "plaster": 2, "terrain": 3, "tiles": 4, "concrete": 5}


# ---------------------------------------------------------------------------- lookup
@dataclass
class Texture:
    """A tileable RGB texture with a mip pyramid (uint8 levels, level 0 is ``size x size``).

    For lookups the levels are packed into one atlas image, each with a 1-texel wrapped border (numba
    kernels in :mod:`mst.pipeline.render_kernels` do the filtered lookups).
    """

    levels: list[np.ndarray]
    texel_m: float  # world size of one level-0 texel, metres
    atlas: np.ndarray = field(default=None, repr=False)
    level_xy: np.ndarray = field(default=None, repr=False)  # (L, 2) atlas position of each level's texel (0, 0)

    def __post_init__(self) -> None:
        if self.atlas is None:
            self.atlas, self.level_xy = _pack_atlas(self.levels)

    @property
    def size(self) -> int:
        return self.levels[0].shape[0]

    @classmethod
    def from_image(cls, img: np.ndarray, texel_m: float) -> Texture:
        """Build the pyramid from a float image in [0, 1] (2x2 box filter per level, tileable)."""
        import cv2

        lev = np.clip(img, 0, 1).astype(np.float32) * np.float32(255.0)
        levels = [np.clip(lev + 0.5, 0, 255).astype(np.uint8)]
        while lev.shape[0] > 4:
            h = lev.shape[0] // 2
            lev = cv2.resize(lev, (h, h), interpolation=cv2.INTER_AREA)  # exact 2x2 box average
            levels.append(np.clip(lev + 0.5, 0, 255).astype(np.uint8))
        return cls(levels, float(texel_m))

    @classmethod
    def generate(cls, kind: str, size: int, texel_m: float, seed: int) -> Texture:
        """Generate texture ``kind`` (one of :data:`GENERATORS`) from ``seed``."""
        rng = np.random.default_rng([int(seed), _STREAM[kind]])
        return cls.from_image(GENERATORS[kind](size, rng), texel_m)

    def sample(self, u: np.ndarray, v: np.ndarray, footprint_texels: np.ndarray) -> np.ndarray:
        """Mip-mapped lookup (bilinear in a level; levels blended over the middle half of each level step).

        ``u``, ``v``: (N,) level-0 texel coordinates (any range, wrapped; texel centres at integers).
        ``footprint_texels``: (N,) size of the pixel footprint in level-0 texels (selects the level).
        Returns (N, 3) float32 RGB in [0, 1]. The renderer's shading kernel does the same lookup
        (:func:`mst.pipeline.render_kernels.texture_sample`).
        """
        return self._sample(u, v, footprint_texels, True)

    def sample_level0(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Plain bilinear lookup in level 0 (for smooth, low-frequency textures): (N, 3) float32 in [0, 1]."""
        return self._sample(u, v, np.ones(len(np.atleast_1d(u)), np.float32), False)

    def _sample(self, u, v, foot, mip: bool) -> np.ndarray:
        from mst.pipeline.render_kernels import sample_points

        u = np.ascontiguousarray(np.atleast_1d(u), np.float32)
        v = np.ascontiguousarray(np.atleast_1d(v), np.float32)
        foot = np.ascontiguousarray(np.broadcast_to(np.asarray(foot, np.float32), u.shape))
        out = np.empty((len(u), 3), np.float32)
        sample_points(self.atlas[None], 0, self.size, len(self.levels), self.level_xy[None], u, v, foot, mip, out)
        return out


def _pack_atlas(levels: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Pack mip levels (each padded by one wrapped texel) into one uint8 image: level 0 on the left,
    the others stacked in a column on its right. Returns the atlas and each level's (x, y) of texel (0, 0)."""
    s0 = levels[0].shape[0]
    W = (s0 + 2) + (s0 // 2 + 2)
    H = max(s0 + 2, sum(lev.shape[0] + 2 for lev in levels[1:]))
    atlas = np.zeros((H, W, 3), np.uint8)
    xy = np.zeros((len(levels), 2), np.float32)
    x, y = 0, 0
    for i, lev in enumerate(levels):
        p = np.pad(lev, ((1, 1), (1, 1), (0, 0)), mode="wrap")
        atlas[y: y + p.shape[0], x: x + p.shape[1]] = p
        xy[i] = (x + 1, y + 1)
        if i == 0:
            x = s0 + 2
        else:
            y += p.shape[0]
    return atlas, xy
