"""SynthCity ground: a top-down road and sidewalk map per route, paved from a city-wide pattern pool.

It models two documented reasons why ground pixels are poor place evidence in VPR:

- perceptual aliasing: asphalt, paving and road markings come from a few patterns shared by the
  whole city (every route, every split), so the ground at one place looks like the ground at many;
- viewpoint sensitivity: the ground is a plane seen in perspective from ``CAM_H`` above it, so a
  lateral camera shift moves ground at distance d by ``FACADE_D / d`` times as many pixels as the
  facades; two traversals of one place rarely show the same piece of road in the same cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

ROAD, SIDEWALK = 0, 1  # Cityscapes trainIds
CAM_H, FACADE_D = 1.6, 15.0  # camera height and facade distance (m)
GROUND_NEAR = 2.5  # nearest ground distance stored (m); the lowest image row sees ~2.8 m
GROUND_PPM = 12.0  # top-down map texels per metre (along the street and in depth)
CURB_Z, SIDEWALK_Z = -0.95, -0.8  # facade-plane heights of the curb's near and far edge (m)
LANE_Z = (-2.9, -2.6)  # facade-plane band of the dashed lane line


def ground_distance(z: np.ndarray | float) -> np.ndarray | float:
    """Distance (m) of the ground point seen through facade-plane height ``z`` < 0."""
    return FACADE_D * CAM_H / (CAM_H - np.asarray(z))


@dataclass(frozen=True)
class GroundPool:
    """Ground patterns shared by the whole dataset: asphalt and paving tiles, painted marks."""

    asphalt: tuple[np.ndarray, ...]  # (th, tw, 3) tiles, repeated by world position
    paving: tuple[np.ndarray, ...]
    marks: tuple[tuple[np.ndarray, np.ndarray], ...]  # (rgb, alpha) stamps painted on the road


@dataclass(frozen=True)
class Ground:
    """Top-down map of one route: row i at distance GROUND_NEAR + (i + 0.5) / GROUND_PPM, column 0 at x0."""

    rgb: np.ndarray  # (D, C, 3) float32
    label: np.ndarray  # (D,) uint8: road, then curb and sidewalk
    x0: float


def _px(metres: float) -> int:
    return max(1, round(metres * GROUND_PPM))


def _asphalt(rng: np.random.Generator) -> np.ndarray:
    """A 3 m asphalt tile: grey with grain, repair patches and a crack, all repeated wherever it is laid."""
    n = _px(3.0)
    tile = np.float32(rng.uniform(0.2, 0.36)) * (1 + rng.uniform(-0.08, 0.08, 3).astype(np.float32))
    tile = np.broadcast_to(tile, (n, n, 3)) + rng.normal(0, 0.06, (n, n, 1)).astype(np.float32)
    yy, xx = np.mgrid[0:n, 0:n]
    for _ in range(int(rng.integers(1, 4))):  # patches of darker or lighter tar
        cy, cx, ry, rx = rng.uniform(0, n, 2).tolist() + rng.uniform(2, n / 3, 2).tolist()
        patch = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 < 1
        tile = np.where(patch[..., None], tile * rng.uniform(0.6, 1.5), tile)
    crack = np.abs(yy - (rng.uniform(0, n) + rng.uniform(-1, 1) * xx + 2 * np.sin(xx / rng.uniform(2, 5)))) < 0.8
    return np.clip(np.where(crack[..., None], tile * 0.4, tile), 0, 1).astype(np.float32)


def _paving(rng: np.random.Generator, kind: int) -> np.ndarray:
    """A seamless paving tile (square slabs, brick bond or diagonal), each paver a shade of a two-colour palette."""
    a, b = (
        np.float32(c) * np.float32(rng.uniform(0.8, 1.1))
        for c in rng.permutation([[0.7, 0.68, 0.64], [0.62, 0.3, 0.24], [0.5, 0.5, 0.52], [0.85, 0.78, 0.6]])[:2]
    )
    if kind == 0:
        cell = _px(float(rng.choice([0.4, 0.6, 0.8])))
        yy, xx = np.mgrid[0 : 4 * cell, 0 : 4 * cell]
        pid, grout = (yy // cell) * 97 + xx // cell, (yy % cell == 0) | (xx % cell == 0)
    elif kind == 1:
        ch, cw = _px(0.2), _px(0.4)
        yy, xx = np.mgrid[0 : 8 * ch, 0 : 5 * cw]
        shifted = (xx + (yy // ch % 2) * (cw // 2)) % (5 * cw)
        pid, grout = (yy // ch) * 97 + shifted // cw, (yy % ch == 0) | (shifted % cw == 0)
    else:
        cell = _px(0.3)
        yy, xx = np.mgrid[0 : 4 * cell, 0 : 4 * cell]
        u, v = (xx + yy) % (4 * cell), (xx - yy) % (4 * cell)
        pid, grout = (u // cell) * 97 + v // cell, (u % cell == 0) | (v % cell == 0)
    shade = rng.uniform(0.85, 1.15, int(pid.max()) + 1).astype(np.float32)[pid]
    tile = np.where((rng.random(int(pid.max()) + 1) < 0.3)[pid][..., None], b, a) * shade[..., None]
    return np.clip(np.where(grout[..., None], tile * 0.45, tile), 0, 1).astype(np.float32)


def _mark(rng: np.random.Generator, kind: int) -> tuple[np.ndarray, np.ndarray]:
    """A painted or metal road mark as (rgb, alpha): arrow, manhole, drain grate, text block or bike symbol."""
    paint = np.float32([0.95, 0.95, 0.92]) if rng.random() < 0.7 else np.float32([0.95, 0.8, 0.15])
    if kind == 0:  # arrow: shaft and head
        h, w = _px(0.9), _px(rng.uniform(2.5, 4.0))
        yy, xx = np.mgrid[0:h, 0:w] / np.float32([[[h]], [[w]]])
        alpha = ((np.abs(yy - 0.5) < 0.15) & (xx < 0.7)) | ((xx >= 0.7) & (np.abs(yy - 0.5) < (1 - xx) * 1.6))
        return np.broadcast_to(paint, (h, w, 3)), alpha
    if kind == 1 or kind == 2:  # manhole cover (disc with a grid) or drain grate (bars)
        n = _px(rng.uniform(0.6, 0.9))
        yy, xx = np.mgrid[0:n, 0:n]
        disc = np.hypot(yy - n / 2 + 0.5, xx - n / 2 + 0.5) < n / 2 if kind == 1 else np.ones((n, n), bool)
        lines = ((yy % 3 == 0) | (xx % 3 == 0)) if kind == 1 else (xx % 2 == 0)
        metal = np.float32([0.12, 0.12, 0.13]) * rng.uniform(0.8, 2.0)
        return np.where(lines[..., None], metal * 1.8, metal).astype(np.float32), disc
    if kind == 3:  # block letters ("BUS", "STOP", ...): a random row of glyph cells
        glyphs = rng.random((5, 3 * int(rng.integers(2, 5)))) < 0.55
        cell = _px(0.2)
        alpha = np.kron(glyphs, np.ones((cell, cell), bool))
        return np.broadcast_to(paint, alpha.shape + (3,)), alpha
    n = _px(1.6)  # bike symbol: two rings and a bar
    yy, xx = np.mgrid[0 : n // 2, 0:n]
    r = n / 5
    rings = [np.abs(np.hypot(yy - n / 4, xx - cx) - r) < 1.2 for cx in (n / 4, 3 * n / 4)]
    alpha = rings[0] | rings[1] | ((np.abs(yy - n / 4) < 1) & (xx > n / 4) & (xx < 3 * n / 4))
    return np.broadcast_to(paint, alpha.shape + (3,)), alpha


def make_ground_pool(rng: np.random.Generator) -> GroundPool:
    """Three asphalts, three pavings and six marks for the whole dataset: the source of ground aliasing."""
    return GroundPool(
        tuple(_asphalt(rng) for _ in range(3)),
        tuple(_paving(rng, k) for k in range(3)),
        tuple(_mark(rng, k % 5) for k in range(6)),
    )


def _lay(
    rgb: np.ndarray,
    rows: slice,
    tiles: tuple[np.ndarray, ...],
    rng: np.random.Generator,
    c0: int,
    run_m: tuple[float, float],
) -> None:
    """Pave ``rows`` in runs of one pool tile each; tiles are indexed by absolute texel position (world-fixed)."""
    cols, c = rgb.shape[1], 0
    r = np.arange(rows.start, rows.stop)
    while c < cols:
        n = _px(rng.uniform(*run_m))
        t = tiles[rng.integers(len(tiles))]
        cc = np.arange(c, min(c + n, cols)) + c0
        rgb[rows, c : c + n] = t[(r % t.shape[0])[:, None], (cc % t.shape[1])[None, :]]
        c += n


def build_ground(rng: np.random.Generator, x0: float, x1: float, pool: GroundPool) -> Ground:
    """Road, curb and sidewalk of one route from the shared pool, with lane dashes and scattered marks."""
    depth = GROUND_NEAR + (np.arange(_px(FACADE_D - GROUND_NEAR)) + 0.5) / GROUND_PPM
    curb, far = np.searchsorted(depth, ground_distance(CURB_Z)), np.searchsorted(depth, ground_distance(SIDEWALK_Z))
    rgb = np.empty((len(depth), _px(x1 - x0), 3), np.float32)
    c0 = round(x0 * GROUND_PPM)
    _lay(rgb, slice(0, curb), pool.asphalt, rng, c0, (15.0, 60.0))
    _lay(rgb, slice(far, len(depth)), pool.paving, rng, c0, (10.0, 40.0))
    rgb[curb:far] = (0.75, 0.75, 0.72)
    lane = slice(*np.searchsorted(depth, ground_distance(np.array(LANE_Z))))
    dash = ((np.arange(rgb.shape[1]) + c0) / GROUND_PPM) % 9.0 < 3.0
    rgb[lane, dash] = 0.9
    x = rng.uniform(0, 8.0)
    while x < x1 - x0:  # marks at fixed places along the street, drawn from the shared pool
        if rng.random() < 0.08:  # zebra crossing: 0.5 m stripes across the whole road, the same everywhere
            cs = slice(_px(x), min(_px(x + rng.uniform(3.0, 4.0)), rgb.shape[1]))  # cut at the route's end
            stripes = ((np.arange(cs.start, cs.stop) + c0) % _px(1.0)) < _px(0.5)
            rgb[:curb, cs] = np.where(stripes[None, :, None], np.float32(0.93), rgb[:curb, cs])
            x += rng.uniform(6.0, 12.0)
            continue
        mrgb, alpha = pool.marks[rng.integers(len(pool.marks))]
        top = (
            int(rng.integers(0, max(1, curb - alpha.shape[0])))
            if rng.random() < 0.8
            else int(rng.integers(far, max(far + 1, len(depth) - alpha.shape[0])))
        )
        left = _px(x)
        window = rgb[top : top + alpha.shape[0], left : left + alpha.shape[1]]
        a = alpha[: window.shape[0], : window.shape[1], None]
        window[:] = np.where(a, mrgb[: window.shape[0], : window.shape[1]], window)
        x += rng.uniform(3.0, 12.0)
    label = np.where(np.arange(len(depth)) < curb, ROAD, SIDEWALK).astype(np.uint8)
    return Ground(rgb, label, x0)


def sample_ground(ground: Ground, z: np.ndarray, x_cam: float, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Colour (n,w,3) and trainIds (n,w) of the ground seen through facade-plane heights ``z`` (n,), all < 0,
    and facade-plane offsets ``u`` (w,) from a camera at street position ``x_cam``: a perspective view."""
    t = ground_distance(z)
    rows = np.clip(((t - GROUND_NEAR) * GROUND_PPM).astype(int), 0, len(ground.label) - 1)
    # The ray through facade point u meets the ground at distance t, i.e. t / FACADE_D of the way out.
    x = x_cam + u[None, :] * (t / FACADE_D)[:, None]
    cols = np.clip(((x - ground.x0) * GROUND_PPM).astype(int), 0, ground.rgb.shape[1] - 1)
    return ground.rgb[rows[:, None], cols], np.broadcast_to(ground.label[rows][:, None], cols.shape)
