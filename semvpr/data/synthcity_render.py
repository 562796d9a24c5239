"""SynthCity drawing: a static street panorama per route, then per-capture crops with a dynamic layer.

Static classes differ in how much they say about the place, each after a documented VPR phenomenon:
facades, poles and signs are the same in both traversals and designed per place (informative);
vegetation changes with the season between the June database and the November query traversal
(foliage colour, leaf loss); road and sidewalk repeat city-wide patterns and are seen in perspective
(``synthcity_ground``: aliasing, viewpoint sensitivity).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from semvpr.data.synthcity_ground import (
    CAM_H,
    CURB_Z,
    FACADE_D,
    SIDEWALK_Z,
    Ground,
    GroundPool,
    build_ground,
    sample_ground,
)

(
    ROAD,
    SIDEWALK,
    BUILDING,
    WALL,
    FENCE,
    POLE,
    LIGHT,
    SIGN,
    VEG,
    TERRAIN,
    SKY,
    PERSON,
    RIDER,
    CAR,
    TRUCK,
    BUS,
    TRAIN,
    MOTORCYCLE,
    BICYCLE,
) = range(19)  # Cityscapes trainIds
DYNAMIC_MIN = SKY  # trainIds >= 10 are dynamic / uninformative (classes.DYNAMIC_NAMES)
TEX_PPM = 6.5  # texture pixels per metre of facade plane
MAX_OBJECT_FRAC = (0.6, 0.65)  # (height, width) cap of one object, as a fraction of the frame
COVERAGE_SPREAD = 0.07  # per-capture std of the coverage target
OVERSHOOT = 0.03  # an object may push the dynamic fraction at most this far past its target

Z_TOP, Z_BOT = 36.0, -8.0  # vertical extent of the panorama, metres in the facade plane
VIEW_BOTTOM = -7.0  # lowest visible ground line (camera 1.6 m high, facade 15 m, near road 2.8 m)
SEASONS = 2  # panorama layers: 0 = database traversal (June foliage), 1 = query traversal (November)

FACADES = np.array(
    [
        [0.80, 0.72, 0.60],
        [0.62, 0.30, 0.22],
        [0.55, 0.55, 0.56],
        [0.88, 0.86, 0.80],
        [0.45, 0.33, 0.25],
        [0.60, 0.72, 0.80],
        [0.65, 0.78, 0.60],
        [0.90, 0.80, 0.45],
        [0.75, 0.55, 0.50],
        [0.35, 0.38, 0.42],
    ],
    np.float32,
)
VIVID = np.array(
    [
        [0.9, 0.1, 0.1],
        [0.1, 0.3, 0.9],
        [0.95, 0.8, 0.1],
        [0.1, 0.7, 0.2],
        [0.9, 0.4, 0.05],
        [0.6, 0.1, 0.7],
        [0.05, 0.7, 0.8],
        [0.95, 0.95, 0.95],
    ],
    np.float32,
)


AUTUMN = np.array(
    [[0.85, 0.72, 0.2], [0.88, 0.5, 0.12], [0.72, 0.22, 0.12], [0.5, 0.36, 0.18]], np.float32
)  # November foliage
POLE_PAINT = np.array([[0.45, 0.45, 0.48], [0.15, 0.3, 0.2], [0.12, 0.12, 0.12], [0.55, 0.5, 0.4]], np.float32)


@dataclass(frozen=True)
class RenderSpec:
    """Camera geometry and difficulty knobs shared by every capture of a dataset."""

    height: int
    width: int
    view_m: float = 24.0  # facade width seen by one capture
    # Calibrated on val (benchmarks/calibrate_synthcity.py --seed 0 1 2: random-init VGG16 + k-means
    # NetVLAD, three draws of the city, v3, default preset at 180x240): binary oracle mask +13.9 ± 3.0 R@1
    # over none, per-class weighted oracle (vegetation, terrain, road, sidewalk at 0) +15.4 ± 2.5 over
    # binary. At 120x160 no knob lifted the binary gain past ~+9.5. coverage 0.64 / lighting 0.15 gave
    # less (one draw at 120x160). Fewer liveries = the same vehicle look at more places. Every knob
    # tried: experiments/synthcity-calibration.
    coverage: float = 0.78  # target dynamic (trainId >= 10) pixel fraction; object caps hold it to ~0.57 measured
    lighting: float = 0.1  # 0 = same light for both traversals, 1 = strong gain/gamma/cast change
    liveries: int = 3  # vehicle/clothing textures shared by the whole dataset
    season: float = 1.0  # vegetation change June -> November: 0 = none, 1 = autumn colours, 30-70 % leaf loss
    jitter_m: float = 3.0
    scale_jitter: float = 0.1
    pitch_m: float = 4.0  # vertical view shift range; larger = more sky, less road

    @property
    def pano_ppm(self) -> float:
        """Panorama pixels per metre: slightly finer than the captures so crops never upsample much."""
        return 1.2 * self.width / self.view_m


@dataclass(frozen=True)
class Panorama:
    """Static world of one route: the facade plane per season (column 0 at ``x0`` m) and the ground."""

    rgb: np.ndarray  # (SEASONS, R, C, 3) float32
    label: np.ndarray  # (SEASONS, R, C) uint8
    ground: Ground
    x0: float
    ppm: float


class _Canvas:
    """Panorama under construction with metre-based drawing primitives."""

    def __init__(self, x0: float, x1: float, ppm: float) -> None:
        self.x0, self.ppm = x0, ppm
        rows, cols = int((Z_TOP - Z_BOT) * ppm), int((x1 - x0) * ppm)
        self.rgb = np.empty((rows, cols, 3), np.float32)
        self.rgb[:] = (0.6, 0.7, 0.9)
        self.label = np.full((rows, cols), SKY, np.uint8)

    def row(self, z: float) -> int:
        return int(np.clip(round((Z_TOP - z) * self.ppm), 0, self.label.shape[0]))

    def col(self, x: float) -> int:
        return int(np.clip(round((x - self.x0) * self.ppm), 0, self.label.shape[1]))

    def box(self, x0: float, x1: float, z0: float, z1: float) -> tuple[slice, slice]:
        return slice(self.row(z1), self.row(z0)), slice(self.col(x0), self.col(x1))

    def rect(self, x0: float, x1: float, z0: float, z1: float, color, cls: int) -> None:
        rs, cs = self.box(x0, x1, z0, z1)
        self.rgb[rs, cs] = color
        self.label[rs, cs] = cls

    def paint(
        self,
        x0: float,
        x1: float,
        z0: float,
        z1: float,
        make: Callable[[int, int], tuple[np.ndarray, np.ndarray]],
        cls: int,
    ) -> None:
        """Blend ``make(h, w) -> (rgb, opacity)`` into the box; pixels of non-zero opacity take class ``cls``."""
        rs, cs = self.box(x0, x1, z0, z1)
        if rs.stop <= rs.start or cs.stop <= cs.start:
            return
        rgb, opacity = make(rs.stop - rs.start, cs.stop - cs.start)
        a = opacity.astype(np.float32)[..., None]
        self.rgb[rs, cs] = a * rgb + (1 - a) * self.rgb[rs, cs]
        self.label[rs, cs] = np.where(opacity > 0, cls, self.label[rs, cs])


@dataclass(frozen=True)
class _Foliage:
    """A tree crown, hedge or lawn, drawn once per season layer after everything behind it."""

    kind: str  # "crown", "hedge" or "lawn"
    box: tuple[float, float, float, float]  # x0, x1, z0, z1 (m)
    june: np.ndarray
    november: np.ndarray
    loss: float  # fraction of the crown bare in November


def _foliage(rng: np.random.Generator, season: float, kind: str, box: tuple[float, float, float, float]) -> _Foliage:
    """Vegetation whose November look moves ``season`` of the way to autumn colour and leaf loss."""
    june = {
        "crown": np.float32([0.2, 0.5, 0.18]),
        "hedge": np.float32([0.2, 0.45, 0.15]),
        "lawn": np.float32([0.35, 0.55, 0.2]),
    }[kind] * np.float32(rng.uniform(0.7, 1.3))
    fall = np.float32([0.62, 0.56, 0.3]) if kind == "lawn" else AUTUMN[rng.integers(len(AUTUMN))]  # straw
    november = june + np.float32(season) * (fall * np.float32(rng.uniform(0.8, 1.1)) - june)
    loss = season * rng.uniform(0.3, 0.7) * {"crown": 1.0, "hedge": 0.4, "lawn": 0.0}[kind]
    return _Foliage(kind, box, june, november, float(loss))


def _draw_foliage(cv: _Canvas, f: _Foliage, rng: np.random.Generator, november: bool) -> None:
    """Paint one vegetation item in one season; its outline (and label) is the same in both."""
    color = f.november if november else f.june
    if f.kind == "lawn":
        cv.rect(*f.box, color, TERRAIN)
        return

    def crown(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
        v, u = _uv(h, w)
        inside = (2 * u - 1) ** 2 + (2 * v - 1) ** 2 <= 1
        rgb = color * (0.75 + 0.5 * rng.random((h, w, 1), dtype=np.float32))
        if not november or f.loss == 0 or not inside.any():
            return rgb, inside.astype(np.float32)
        # Leaves fall in clumps about a metre across (the bare share is exactly ``loss``). A bare patch is
        # a see-through tangle of twigs: still vegetation, as Cityscapes labels bare crowns, but it lets
        # what is behind show through.
        clumps = bilinear_noise(rng, h, w, max(2, round(h / cv.ppm)), max(2, round(w / cv.ppm)))
        bare = inside & (clumps < np.quantile(clumps[inside], f.loss))
        twigs = bilinear_noise(rng, h, w, max(2, round(h / cv.ppm * 3)), max(2, round(w / cv.ppm * 3))) > 0.55
        rgb = np.where((bare & twigs)[..., None], np.float32([0.25, 0.18, 0.12]), rgb)
        alpha = np.where(bare, np.where(twigs, 0.9, 0.25), 1.0) * inside
        return rgb, alpha.astype(np.float32)

    cv.paint(*f.box, crown, VEG)


def _sign_face(rng: np.random.Generator, h: int, w: int, board: bool) -> tuple[np.ndarray, np.ndarray]:
    """A sign designed for its place: shape, two colours and a glyph grid of its own."""
    v, u = _uv(h, w)
    shape = int(rng.integers(4)) if not board else 0
    du, dv = np.abs(u - 0.5), np.abs(v - 0.5)
    mask = np.broadcast_to(
        [np.ones((1, 1), bool), du**2 + dv**2 <= 0.25, du + dv <= 0.5, (v >= 0.05) & (du <= 0.5 * v)][shape], (h, w)
    )
    gh, gw = (2, 6) if board else (3, 3)
    glyph = rng.random((gh, gw)) < 0.5
    inner = (du < 0.3) & (dv < 0.25)
    row, col = ((v - 0.25) / 0.5 * gh).clip(0, gh - 1), ((u - 0.2) / 0.6 * gw).clip(0, gw - 1)
    cell = glyph[row.astype(int), col.astype(int)]
    a, b = _vivid(rng), _vivid(rng)
    return np.where((inner & cell)[..., None], b, a), mask


def _building(cv: _Canvas, rng: np.random.Generator, x0: float, x1: float, h: float) -> None:
    """Facade with a window grid, a ground floor (shop front with sign, or door) and a cornice."""
    base = FACADES[rng.integers(len(FACADES))] * rng.uniform(0.85, 1.1)
    rs, cs = cv.box(x0, x1, 0.0, h)
    cv.rect(x0, x1, 0.0, h, base, BUILDING)
    rr, cc = np.arange(rs.stop - rs.start)[:, None], np.arange(cs.stop - cs.start)[None, :]
    if rng.random() < 0.35:  # brick courses: fine horizontal texture unique to this facade
        period = max(2, int(rng.uniform(0.3, 0.6) * cv.ppm))
        cv.rgb[rs, cs] *= np.where(rr % period == 0, 0.8, 1.0)[..., None]
    floor_h, col_w = rng.uniform(2.8, 3.8), rng.uniform(1.8, 3.4)
    fy, fx = max(3, int(floor_h * cv.ppm)), max(3, int(col_w * cv.ppm))
    wy0, wy1 = int(fy * rng.uniform(0.2, 0.35)), int(fy * rng.uniform(0.65, 0.85))
    wx0 = int(fx * rng.uniform(0.15, 0.3))
    wx1 = max(wx0 + 1, int(fx * rng.uniform(0.6, 0.85)))
    # Rows counted from the ground up so floors line up with the street.
    up = (rs.stop - rs.start - 1) - rr
    win = ((up % fy) >= fy - wy1) & ((up % fy) < fy - wy0) & ((cc % fx) >= wx0) & ((cc % fx) < wx1)
    win &= (up >= fy) & (cc >= fx // 3) & (cc < cc.shape[1] - fx // 3)
    glass = np.array([0.15, 0.2, 0.3], np.float32) * rng.uniform(0.6, 2.0, 3).astype(np.float32)
    # Per-window brightness (lit rooms, curtains) makes each facade distinctive.
    lit = rng.uniform(0.6, 1.9, (up.max() // fy + 2, cc.shape[1] // fx + 2)).astype(np.float32)
    tint = lit[up // fy, cc // fx][..., None] * glass
    cv.rgb[rs, cs] = np.where(win[..., None], np.clip(tint, 0, 1), cv.rgb[rs, cs])
    # Upper-floor details, so a facade stays recognisable when traffic hides its ground floor.
    if rng.random() < 0.4:  # storeys painted in alternating colours
        odd = ((up // fy) % 2 == 1) & ~win
        cv.rgb[rs, cs] = np.where(odd[..., None], base * rng.uniform(0.6, 1.3, 3).astype(np.float32), cv.rgb[rs, cs])
    if rng.random() < 0.4:  # balconies / flower boxes under the windows
        sill = ((up % fy) >= fy - wy0) & ((up % fy) < fy - wy0 + max(1, fy // 6))
        sill = sill & ((cc % fx) >= wx0 - 1) & ((cc % fx) <= wx1) & (up >= fy) & (up < up.max() - fy // 2)
        cv.rgb[rs, cs] = np.where(sill[..., None], _vivid(rng) * rng.uniform(0.5, 1.0), cv.rgb[rs, cs])
    if h > 9 and rng.random() < 0.35:  # mural or billboard
        bw = min(x1 - x0 - 1.0, rng.uniform(3.0, 8.0))
        bx, bz = rng.uniform(x0 + 0.5, x1 - 0.5 - bw), rng.uniform(4.0, h - 4.0)
        for j, c in enumerate([_vivid(rng) for _ in range(3)]):
            cv.rect(bx + j * bw / 3, bx + (j + 1) * bw / 3, bz, bz + rng.uniform(1.5, 3.0), c, BUILDING)
    g = min(floor_h, h) * 0.9
    if rng.random() < 0.5:  # shop front: display window and a vivid sign band
        cv.rect(x0 + 0.6, x1 - 0.6, 0.2, g * 0.62, glass * 1.4, BUILDING)
        sign = VIVID[rng.integers(len(VIVID))]
        cv.rect(x0 + 0.4, x1 - 0.4, g * 0.68, g * 0.95, sign, BUILDING)
        srs, scs = cv.box(x0 + 0.8, x1 - 0.8, g * 0.74, g * 0.89)
        letters = (np.arange(scs.stop - scs.start) % max(2, int(0.45 * cv.ppm))) < int(0.3 * cv.ppm)
        cv.rgb[srs, scs] = np.where(letters[None, :, None], 1.0 - sign, cv.rgb[srs, scs])
    else:
        d = rng.uniform(x0 + 0.5, max(x0 + 0.6, x1 - 1.8))
        cv.rect(d, d + 1.2, 0.0, min(2.3, g), np.float32([0.3, 0.2, 0.12]) * rng.uniform(0.5, 1.5), BUILDING)
    cv.rect(x0, x1, h - 0.4, h, base * 0.6, BUILDING)


def _gap(cv: _Canvas, rng: np.random.Generator, x0: float, x1: float, season: float, veg: list[_Foliage]) -> None:
    """Space between buildings: a distant building or sky, behind a wall, fence or hedge on a lawn."""
    if rng.random() < 0.5:
        cv.rect(x0, x1, 0.0, rng.uniform(8, 30), FACADES[rng.integers(len(FACADES))] * 0.8 + 0.15, BUILDING)
    veg.append(_foliage(rng, season, "lawn", (x0, x1, 0.0, 0.3)))
    kind, top = rng.integers(3), rng.uniform(1.2, 2.6)
    if kind == 0:
        cv.rect(x0, x1, 0.3, top, np.float32([0.7, 0.68, 0.62]) * rng.uniform(0.7, 1.1), WALL)
    elif kind == 1:
        rs, cs = cv.box(x0, x1, 0.3, top)
        bars = (np.arange(cs.stop - cs.start) % max(2, int(0.3 * cv.ppm))) == 0
        bars[:1] = True
        bars = bars[None, :] | (np.arange(rs.stop - rs.start)[:, None] == 0)
        cv.rgb[rs, cs] = np.where(bars[..., None], np.float32(0.2), cv.rgb[rs, cs])
        cv.label[rs, cs] = np.where(bars, FENCE, cv.label[rs, cs])
    else:
        veg.append(_foliage(rng, season, "hedge", (x0, x1, 0.3, 2 * top - 0.3)))


def _furniture(cv: _Canvas, rng: np.random.Generator, x: float, season: float, veg: list[_Foliage]) -> None:
    """One item along the curb at street position ``x``: a tree, or a pole with signs or a traffic light."""
    kind = rng.random()
    if kind < 0.55:
        zc, rx, rz = rng.uniform(6.0, 10.0), rng.uniform(2.5, 4.5), rng.uniform(2.5, 4.0)
        cv.rect(x - 0.15, x + 0.15, -0.6, zc, [0.3, 0.22, 0.15], VEG)
        veg.append(_foliage(rng, season, "crown", (x - rx, x + rx, zc - rz, zc + rz)))
        return
    top = rng.uniform(6.0, 8.5)
    cv.rect(x - 0.1, x + 0.1, -0.6, top, POLE_PAINT[rng.integers(len(POLE_PAINT))], POLE)
    if kind < 0.85:  # one or two signs (traffic signs or street-name boards), each designed for this place
        z = rng.uniform(2.2, 3.0)
        for _ in range(int(rng.integers(1, 3))):
            board = bool(rng.random() < 0.35)
            sw = rng.uniform(2.0, 3.2) if board else rng.uniform(0.8, 1.4)
            sh = rng.uniform(0.7, 1.2) if board else sw
            cv.paint(x - sw / 2, x + sw / 2, z, z + sh, lambda h, w, b=board: _sign_face(rng, h, w, b), SIGN)
            z += sh + 0.15
    elif kind < 0.95:
        cv.rect(x - 0.2, x + 0.2, top - 1.1, top, [0.1, 0.1, 0.1], LIGHT)
        lamp = rng.integers(3)
        cv.rect(
            x - 0.1,
            x + 0.1,
            top - 0.95 + 0.33 * lamp,
            top - 0.75 + 0.33 * lamp,
            [[0.1, 1, 0.2], [1, 0.8, 0], [1, 0.1, 0.1]][lamp],
            LIGHT,
        )


def build_panorama(rng: np.random.Generator, length_m: float, spec: RenderSpec, ground_pool: GroundPool) -> Panorama:
    """Draw the static street of one route: buildings, gaps, street furniture, vegetation per season, ground."""
    margin = spec.view_m * (1 + spec.scale_jitter) / 2 + spec.jitter_m + 2.0
    cv = _Canvas(-margin, length_m + margin, spec.pano_ppm)
    end = length_m + margin
    veg: list[_Foliage] = []
    x = -margin
    while x < end:
        if rng.random() < 0.3:
            w = rng.uniform(1.5, 5.0)
            _gap(cv, rng, x, x + w, spec.season, veg)
            x += w
        w, kind = rng.uniform(6.0, 22.0), rng.random()
        h = rng.uniform(4, 10) if kind < 0.35 else rng.uniform(10, 17) if kind < 0.75 else rng.uniform(17, 32)
        _building(cv, rng, x, x + w, h)
        x += w
    # Ground bands only as labels here: render_capture draws road and sidewalk in perspective from Ground.
    cv.rect(-margin, end, SIDEWALK_Z, 0.0, 0.0, SIDEWALK)
    cv.rect(-margin, end, Z_BOT, CURB_Z, 0.0, ROAD)
    cv.rect(-margin, end, CURB_Z, SIDEWALK_Z, 0.0, SIDEWALK)
    x = -margin + rng.uniform(0, 10)
    while x < end:
        _furniture(cv, rng, x, spec.season, veg)
        x += rng.uniform(6.0, 18.0)
    # Static grain: fixed per route, so it is part of the place, not of the capture.
    grain = rng.normal(0, 0.03, cv.rgb.shape[:2] + (1,)).astype(np.float32)
    base_rgb, base_label = cv.rgb, cv.label
    rgb, label = np.empty((SEASONS,) + base_rgb.shape, np.float32), np.empty((SEASONS,) + base_label.shape, np.uint8)
    for season in range(SEASONS):
        cv.rgb, cv.label = base_rgb.copy(), base_label.copy()
        for f in veg:
            _draw_foliage(cv, f, rng, november=season == 1)
        rgb[season], label[season] = np.clip(cv.rgb + grain, 0, 1), cv.label
    return Panorama(rgb, label, build_ground(rng, -margin, end, ground_pool), cv.x0, cv.ppm)


# Weather: (top, bottom) sky colour ranges; a capture draws uniformly inside one of them.
WEATHERS = (
    ((0.15, 0.35, 0.75), (0.35, 0.55, 0.95), (0.6, 0.72, 0.9), (0.8, 0.88, 1.0)),  # clear
    ((0.45, 0.45, 0.48), (0.8, 0.8, 0.84), (0.55, 0.55, 0.58), (0.9, 0.9, 0.92)),  # overcast
    ((0.12, 0.14, 0.2), (0.3, 0.32, 0.4), (0.3, 0.32, 0.36), (0.5, 0.52, 0.56)),  # storm
    ((0.25, 0.2, 0.45), (0.45, 0.35, 0.65), (0.85, 0.45, 0.2), (1.0, 0.7, 0.4)),  # sunset
    ((0.7, 0.68, 0.55), (0.85, 0.82, 0.7), (0.85, 0.8, 0.65), (0.98, 0.95, 0.85)),
)  # haze


def _sky(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Weather-tinted sky with high-contrast clouds, drawn fresh per capture (sky is not part of the place)."""
    tlo, thi, blo, bhi = (np.float32(c) for c in WEATHERS[rng.integers(len(WEATHERS))])
    top, bottom = rng.uniform(tlo, thi).astype(np.float32), rng.uniform(blo, bhi).astype(np.float32)
    t = np.linspace(0, 1, h, dtype=np.float32)[:, None, None]
    sky = (1 - t) * top + t * bottom
    cover = (bilinear_noise(rng, h, w, 6, 8) - rng.uniform(0.2, 0.7)) * rng.uniform(1.5, 4.0)
    clouds = np.clip(cover, 0, 1)[..., None]
    return sky * (1 - clouds) + np.float32(rng.uniform(0.3, 1.0)) * clouds


def render_capture(
    pano: Panorama,
    x: float,
    rng: np.random.Generator,
    spec: RenderSpec,
    pool: np.ndarray,
    query: bool,
    lighting: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One capture around route position ``x``: (H,W,3) uint8 image and (H,W) uint8 trainIds.

    Query captures see the November panorama layer and a stronger lighting change. ``lighting`` scales
    ``spec.lighting`` for this capture (None: 1 for a query, 0.25 for the database traversal); the
    random draws are the same whatever it is."""
    h, w = spec.height, spec.width
    ppm = w / (spec.view_m * (1 + rng.uniform(-spec.scale_jitter, spec.scale_jitter)))
    xc = x + rng.uniform(-spec.jitter_m, spec.jitter_m)
    z_top = VIEW_BOTTOM + rng.uniform(0, spec.pitch_m) + h / ppm
    u = (np.arange(w) + 0.5 - w / 2) / ppm  # facade-plane offset of each column from the camera
    z = z_top - (np.arange(h) + 0.5) / ppm  # facade-plane height of each row
    cols = np.clip(((xc + u - pano.x0) * pano.ppm).astype(int), 0, pano.label.shape[2] - 1)
    rows = np.clip(((Z_TOP - z) * pano.ppm).astype(int), 0, pano.label.shape[1] - 1)
    layer = int(query)
    rgb = pano.rgb[layer][rows[:, None], cols[None, :]]
    label = pano.label[layer][rows[:, None], cols[None, :]]
    below = slice(int(np.searchsorted(-z, 0.0, side="right")), h)  # rows under the facade base see the ground
    g_rgb, g_label = sample_ground(pano.ground, z[below], xc, u)
    ground = (label[below] == ROAD) | (label[below] == SIDEWALK)  # not tree trunks or poles standing there
    rgb[below] = np.where(ground[..., None], g_rgb, rgb[below])
    label[below] = np.where(ground, g_label, label[below])
    rgb = np.where((label == SKY)[..., None], _sky(rng, h, w), rgb).astype(np.float32)
    target = float(np.clip(spec.coverage + rng.normal(0, COVERAGE_SPREAD), 0.05, 0.9))
    add_dynamic_objects(rgb, label, rng, pool, ppm, z_top, target)
    # Lighting: the query traversal is at another time of day; the database one varies a little.
    d = spec.lighting * ((1.0 if query else 0.25) if lighting is None else lighting)
    gain = rng.uniform(1 - 0.5 * d, 1 + 0.3 * d)
    gamma = np.exp(rng.uniform(-0.4 * d, 0.4 * d))
    cast = rng.uniform(-0.12 * d, 0.12 * d, 3).astype(np.float32)
    rgb = gain * np.clip(rgb, 0, 1) ** gamma + cast
    rgb += rng.normal(0, 0.01 + 0.03 * d, rgb.shape).astype(np.float32)
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8), label


def bilinear_noise(rng: np.random.Generator, h: int, w: int, gh: int, gw: int) -> np.ndarray:
    """Smooth (h,w) noise in [0,1]: a coarse (gh+1,gw+1) random grid, bilinearly upsampled."""
    grid = rng.random((gh + 1, gw + 1), dtype=np.float32)
    y, x = np.linspace(0, gh, h, dtype=np.float32), np.linspace(0, gw, w, dtype=np.float32)
    y0, x0 = np.minimum(y.astype(int), gh - 1), np.minimum(x.astype(int), gw - 1)
    fy, fx = (y - y0)[:, None], (x - x0)[None, :]
    top = grid[y0][:, x0] * (1 - fx) + grid[y0][:, x0 + 1] * fx
    bot = grid[y0 + 1][:, x0] * (1 - fx) + grid[y0 + 1][:, x0 + 1] * fx
    return top * (1 - fy) + bot * fy


def _vivid(rng: np.random.Generator) -> np.ndarray:
    """A saturated random colour (hue wheel)."""
    hue = np.clip(np.abs((rng.random() * 6 + np.array([0.0, 4.0, 2.0])) % 6 - 3) - 1, 0, 1)
    s, v = rng.uniform(0.7, 1.0), rng.uniform(0.7, 1.0)
    return (v * (1 - s + s * hue)).astype(np.float32)


def make_texture_pool(rng: np.random.Generator, n: int, th: int = 48, tw: int = 96) -> np.ndarray:
    """Vivid vehicle/clothing textures shared by the whole dataset, so one livery shows up at many places."""
    yy, xx = np.mgrid[0:th, 0:tw].astype(np.float32)
    pool = np.empty((n, th, tw, 3), np.float32)
    for i in range(n):
        a, b, c = _vivid(rng), _vivid(rng), _vivid(rng)
        kind = i % 5
        if kind == 0:  # stripes at a random angle
            ang, per = rng.uniform(0, np.pi), rng.uniform(4, 16)
            t = ((xx * np.cos(ang) + yy * np.sin(ang)) / per) % 3
            tex = np.where((t < 1)[..., None], a, np.where((t < 2)[..., None], b, c))
        elif kind == 1:  # checker
            cell = int(rng.integers(4, 12))
            tex = np.where((((yy // cell) + (xx // cell)) % 2 == 0)[..., None], a, b)
        elif kind == 2:  # dots
            per = rng.uniform(6, 14)
            d = ((yy % per) - per / 2) ** 2 + ((xx % per) - per / 2) ** 2
            tex = np.where((d < (per / 3) ** 2)[..., None], a, b)
        elif kind == 3:  # advertising wrap: big ellipses on a background
            tex = np.broadcast_to(a, (th, tw, 3)).copy()
            for _ in range(3):
                cy, cx, ry, rx = rng.uniform(0, th), rng.uniform(0, tw), rng.uniform(4, th), rng.uniform(6, tw / 2)
                tex[((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 < 1] = _vivid(rng)
        else:  # solid paint with a highlight band
            tex = np.broadcast_to(a, (th, tw, 3)) * (0.8 + 0.3 * (np.abs(yy - th * 0.4) < th * 0.1))[..., None]
        pool[i] = tex
    return np.clip(pool, 0, 1)


def _uv(ph: int, pw: int) -> tuple[np.ndarray, np.ndarray]:
    return (np.arange(ph) + 0.5)[:, None] / ph, (np.arange(pw) + 0.5)[None, :] / pw


def _disc(ph: int, pw: int, cu: float, cv: float, r_px: float, inner: float = 0.0) -> np.ndarray:
    """Disc (or ring when ``inner`` > 0) of radius ``r_px`` at fractional centre (cu, cv) of a patch."""
    out = np.zeros((ph, pw), bool)
    cy, cx = cv * ph, cu * pw
    rs = slice(max(0, int(cy - r_px)), min(ph, int(np.ceil(cy + r_px)) + 1))  # only the disc's bounding box
    cs = slice(max(0, int(cx - r_px)), min(pw, int(np.ceil(cx + r_px)) + 1))
    d = np.hypot(np.arange(rs.start, rs.stop)[:, None] + 0.5 - cy, np.arange(cs.start, cs.stop)[None, :] + 0.5 - cx)
    out[rs, cs] = (d <= r_px) & (d >= inner * r_px)
    return out


def _tex(pool: np.ndarray, rng: np.random.Generator, ph: int, pw: int, ppm: float) -> np.ndarray:
    """A pool texture tiled at a fixed metric scale: one livery looks the same on any vehicle, anywhere."""
    t = pool[rng.integers(len(pool))]
    step = TEX_PPM / ppm
    rows = ((np.arange(ph) + rng.integers(t.shape[0])) * step).astype(int) % t.shape[0]
    cols = ((np.arange(pw) + rng.integers(t.shape[1])) * step).astype(int) % t.shape[1]
    return t[rows][:, cols]


Paint = Callable[[], np.ndarray]  # colours of a road user's patch, drawn only once it is placed


class _Part(NamedTuple):
    """One patch of a road user: its colours, its pixel shape, its trainId and where its top-left corner goes."""

    paint: Paint
    shape: np.ndarray
    cls: int
    top: int
    left: int


def _vehicle(
    cls: int, ph: int, pw: int, rng: np.random.Generator, pool: np.ndarray, ppm: float
) -> tuple[Paint, np.ndarray]:
    """Car / bus / truck side view: textured body, dark glass, wheels; returns (paint, shape mask)."""
    v, u = _uv(ph, pw)
    if cls == CAR:
        slope = (0.42 - v) / 0.42
        cabin = (v <= 0.42) & (u > 0.22 + 0.12 * slope) & (u < 0.8 - 0.1 * slope)
        shape = ((v > 0.42) & (v < 0.9)) | cabin
        win = cabin & (v > 0.1) & (np.abs(u - 0.52) > 0.02) & (u > 0.27) & (u < 0.76)
        centres = (0.2, 0.8)
    elif cls == BUS:
        shape = np.broadcast_to(v < 0.9, (ph, pw))
        win = (v > 0.12) & (v < 0.45) & ((u * 9) % 1 > 0.12)
        centres = (0.13, 0.87)
    else:
        shape = ((u < 0.74) & (v < 0.88)) | ((u > 0.76) & (v > 0.3) & (v < 0.9))
        win = (u > 0.8) & (v > 0.35) & (v < 0.55)
        centres = (0.15, 0.4, 0.86)
    r = 0.12 * ph if cls != CAR else 0.13 * ph
    wheels = np.zeros((ph, pw), bool)
    for cu in centres:
        wheels |= _disc(ph, pw, cu, 1 - r / ph, r)
    flip = rng.random() < 0.5  # driving the other way

    def paint() -> np.ndarray:
        rgb = _tex(pool, rng, ph, pw, ppm).copy()
        rgb[np.broadcast_to(win, (ph, pw))] = (0.12, 0.15, 0.2)
        rgb[wheels] = 0.08
        return rgb[:, ::-1] if flip else rgb

    shape = shape | wheels
    return paint, shape[:, ::-1] if flip else shape


def _person(
    ph: int, pw: int, rng: np.random.Generator, pool: np.ndarray, ppm: float, seated: bool = False
) -> tuple[Paint, np.ndarray]:
    """Pedestrian (or seated rider): head, textured torso, legs."""
    v, u = _uv(ph, pw)
    head = ((u - 0.5) / 0.3) ** 2 + ((v - 0.08) / 0.08) ** 2 <= 1
    torso = (v > 0.15) & (v <= (0.7 if seated else 0.55)) & (u > 0.08) & (u < 0.92)
    legs = (v > 0.55) & (u > 0.15) & (u < 0.85) & ((u < 0.45) | (u > 0.55) | seated)

    def paint() -> np.ndarray:
        rgb = np.empty((ph, pw, 3), np.float32)
        rgb[:] = _vivid(rng) * rng.uniform(0.2, 0.6)
        rgb[torso] = _tex(pool, rng, ph, pw, ppm)[torso]
        rgb[head] = np.float32([0.85, 0.65, 0.5]) * rng.uniform(0.5, 1.1)
        return rgb

    return paint, head | torso | legs


def _two_wheeler(ph: int, pw: int, rng: np.random.Generator, motor: bool) -> tuple[Paint, np.ndarray]:
    """Bicycle (rings and a frame) or motorcycle (filled body) side view."""
    v, u = _uv(ph, pw)
    r = min(0.22 * pw, 0.45 * ph)
    shape = _disc(ph, pw, 0.2, 1 - r / ph, r, 0.0 if motor else 0.7)
    shape |= _disc(ph, pw, 0.8, 1 - r / ph, r, 0.0 if motor else 0.7)
    frame = (v > 0.35) & (v < 0.8) & (u > 0.25) & (u < 0.75)
    shape |= frame if motor else frame & (np.abs(v - 0.4 - 0.4 * np.abs(u - 0.5)) < 0.12)

    def paint() -> np.ndarray:
        rgb = np.empty((ph, pw, 3), np.float32)
        rgb[:] = _vivid(rng) if motor else np.float32(0.15)
        return rgb

    return paint, shape


def _paste(rgb, label, zbuf, part: _Part, depth: float, commit: bool = True) -> int:
    """Composite a patch at its (top, left) where it is nearer than what is there; returns new dynamic pixels."""
    paint, shape, cls, top, left = part
    h, w = label.shape
    r0, c0 = max(top, 0), max(left, 0)
    r1, c1 = min(top + shape.shape[0], h), min(left + shape.shape[1], w)
    if r1 <= r0 or c1 <= c0:
        return 0
    m = shape[r0 - top : r1 - top, c0 - left : c1 - left] & (zbuf[r0:r1, c0:c1] > depth)
    new = int((m & (label[r0:r1, c0:c1] < DYNAMIC_MIN)).sum())
    if commit:
        rgb[r0:r1, c0:c1][m] = paint()[r0 - top : r1 - top, c0 - left : c1 - left][m]
        label[r0:r1, c0:c1][m] = cls
        zbuf[r0:r1, c0:c1][m] = depth
    return new


# kind, probability, depth range (m), length (m), height (m). Mostly big, near vehicles: whole feature
# cells then show only a (shared, misleading) livery, which is what a static mask can remove.
_KINDS = (
    (CAR, 0.35, (4.0, 7.0), (4.0, 4.9), (1.4, 1.6)),
    (BUS, 0.25, (5.0, 8.0), (10.0, 12.0), (3.0, 3.4)),
    (TRUCK, 0.2, (5.0, 8.0), (7.0, 10.0), (2.8, 3.6)),
    (PERSON, 0.12, (9.0, 13.0), (0.5, 0.65), (1.6, 1.9)),
    (RIDER, 0.08, (7.0, 9.0), (1.6, 2.0), (1.0, 1.15)),
)


#: Most road users in one image, and how many draws may try to place them.
MAX_OBJECTS, PLACEMENT_TRIES = 12, 30


def _sample_object(rng: np.random.Generator, pool: np.ndarray, ppm: float, z_top: float, h: int, w: int):
    """One random road user as (depth, parts); a part is (paint, shape, trainId, top, left)."""
    probs = np.array([k[1] for k in _KINDS])
    cls, _, depth, length, height = _KINDS[rng.choice(len(_KINDS), p=probs / probs.sum())]
    d = rng.uniform(*depth)
    k = FACADE_D / d
    # Caps keep one bus from covering most of the frame (coverage must stay controllable).
    pw = max(2, round(min(rng.uniform(*length) * k * ppm, MAX_OBJECT_FRAC[1] * w)))
    ph = max(3, round(min(rng.uniform(*height) * k * ppm, MAX_OBJECT_FRAC[0] * h)))
    ground = round((z_top - CAM_H * (1 - k)) * ppm)  # image row where the object meets the road
    left = round(w / 2 + rng.uniform(-0.5, 0.5) * (w + pw)) - pw // 2
    if cls in (CAR, BUS, TRUCK):
        return d, [_Part(*_vehicle(cls, ph, pw, rng, pool, ppm), cls, ground - ph, left)]
    if cls == PERSON:
        return d, [_Part(*_person(ph, pw, rng, pool, ppm), cls, ground - ph, left)]
    motor = rng.random() < 0.3
    rh, rw = round(1.5 / 1.05 * ph), max(2, round(pw * 0.35))
    return d, [
        _Part(*_two_wheeler(ph, pw, rng, motor), MOTORCYCLE if motor else BICYCLE, ground - ph, left),
        _Part(
            *_person(rh, rw, rng, pool, ppm, seated=True), RIDER, ground - round(0.45 * ph) - rh, left + round(0.3 * pw)
        ),
    ]


def add_dynamic_objects(
    rgb: np.ndarray,
    label: np.ndarray,
    rng: np.random.Generator,
    pool: np.ndarray,
    ppm: float,
    z_top: float,
    target: float,
) -> None:
    """Add road users (in place) until the MEASURED dynamic pixel fraction reaches ``target`` (at most
    ``MAX_OBJECTS`` of them, in ``PLACEMENT_TRIES`` draws)."""
    h, w = label.shape
    zbuf = np.full((h, w), 99.0, np.float32)  # static scene is at ~15 m: anything nearer occludes it
    dyn, limit = int((label >= DYNAMIC_MIN).sum()), (target + OVERSHOOT) * label.size
    placed = 0
    for _ in range(PLACEMENT_TRIES):
        if placed >= MAX_OBJECTS or dyn >= target * label.size:
            break
        d, parts = _sample_object(rng, pool, ppm, z_top, h, w)
        new = sum(_paste(rgb, label, zbuf, part, d, commit=False) for part in parts)
        if new == 0 or dyn + new > limit:  # would overshoot: try a smaller or better-placed one
            continue
        for part in parts:
            _paste(rgb, label, zbuf, part, d)
        dyn, placed = int((label >= DYNAMIC_MIN).sum()), placed + 1
