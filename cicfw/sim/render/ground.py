"""Top-down ground textures: one per town (what is road, markings, sidewalk, terrain), then one per
town x weather (light, baked shadows of buildings and trees, wet darkening, puddles) with a mip
pyramid the cameras warp from.

Markings are asymmetric on purpose, so a mirrored world cannot pass for a correct one: the centre
line (yellow, or dashed when the town's centre line is white) is on the driver's left, solid edge
lines on the right, and stop lines cross only the incoming lane at every junction, behind a zebra
crossing. The texture's row 0 is the north edge (the texture is a north-up map).
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import cv2
import numpy as np

from cicfw.sim.render.noise import fbm, smooth_noise, stable_seed
from cicfw.sim.render.weather import Weather
from cicfw.sim.town.geometry import frames_at

RES = 0.1  # m per texel at level 0
LEVELS = 7  # mip levels: 0.1 m .. 6.4 m per texel

# Layout of markings near a junction (metres from the junction's edge, along the road)
ZEBRA = (0.6, 3.4)
STOP = (3.9, 4.3)
LINES_FROM = 4.6
STRIPE_W, STRIPE_GAP = 0.5, 0.55
DASH, DASH_GAP = 3.0, 3.0

# per-class wetness response: how much darker when soaked, base reflectivity when wet
_TERRAIN, _SIDEWALK, _ROAD, _MARK = range(4)
_WET_DARK = {_TERRAIN: 0.3, _SIDEWALK: 0.3, _ROAD: 0.4, _MARK: 0.15}
_WET_REFL = {_TERRAIN: 0.04, _SIDEWALK: 0.35, _ROAD: 0.65, _MARK: 0.45}


@dataclass(eq=False)
class GroundBase:
    """Weather-independent ground of one town: albedo and wet response per texel."""

    x0: float  # world x of the texture's left edge
    y1: float  # world y of the texture's top edge (north)
    res: float
    albedo: np.ndarray  # (H, W, 3) uint8 RGB
    wet_dark: np.ndarray  # (H, W) uint8: fraction of albedo lost when soaked (x255)
    wet_refl: np.ndarray  # (H, W) uint8 reflectivity when soaked
    puddle: np.ndarray  # (H, W) uint8 puddle potential (low spots, gutters)
    border: tuple  # terrain colour beyond the texture (RGB 0-255)

    @property
    def shape(self) -> tuple[int, int]:
        return self.albedo.shape[:2]

    def world_to_texel(self) -> np.ndarray:
        """3x3: world (x, y, 1) -> texel (col, row, 1), texel centres at integers."""
        r = self.res
        return np.array([[1 / r, 0, -self.x0 / r - 0.5], [0, -1 / r, self.y1 / r - 0.5], [0, 0, 1.0]])

    def px(self, pts: np.ndarray) -> np.ndarray:
        """World points (N, 2) -> fixed-point texel coordinates (shift 4) for cv2 drawing."""
        p = np.asarray(pts, float)
        q = np.stack([(p[:, 0] - self.x0) / self.res - 0.5, (self.y1 - p[:, 1]) / self.res - 0.5], 1)
        return np.round(q * 16).astype(np.int32)


@dataclass(eq=False)
class GroundTexture:
    """The baked ground of one town under one weather: RGBA pyramid (A = reflectivity when wet)."""

    base: GroundBase
    pyramid: list  # level 0..LEVELS-1 of (H/2^l, W/2^l, 4) uint8
    borders: list  # per level border value (RGBA)


_BASE_CACHE: dict = {}


def ground_base(town, res: float = RES) -> GroundBase:
    """The (cached per town object) weather-independent ground of ``town``."""
    key = (id(town), res)
    hit = _BASE_CACHE.get(key)
    if hit is not None and hit[0]() is town:
        return hit[1]
    base = bake_base(town, res)
    try:
        ref = weakref.ref(town)
    except TypeError:  # an object without weakref support: keep it alive instead
        ref = (lambda t: (lambda: t))(town)
    _BASE_CACHE[key] = (ref, base)
    return base


def _length(c: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())


def _offset_line(c: np.ndarray, s0: float, s1: float, off: float, step: float = 0.5) -> np.ndarray:
    s = np.linspace(s0, s1, max(int(math.ceil((s1 - s0) / step)), 1) + 1)
    p, _, n = frames_at(c, s)
    return p + off * n


def _quad(c: np.ndarray, s0: float, s1: float, o0: float, o1: float) -> np.ndarray:
    p, _, n = frames_at(c, np.array([s0, s1]))
    return np.array([p[0] + o0 * n[0], p[1] + o0 * n[1], p[1] + o1 * n[1], p[0] + o1 * n[0]])


def _draw_markings(town, base_px, shape) -> tuple[np.ndarray, np.ndarray]:
    """(centre-line mask, white mask) uint8, anti-aliased."""
    lw = town.lane_width
    junction_ids = {j.id for j in town.junctions if len(j.arms) >= 3}
    yellow = np.zeros(shape, np.uint8)
    white = np.zeros(shape, np.uint8)
    st = town.style
    dashed_centre = tuple(st.centre_line) == tuple(st.marking)
    centre_mask = white if dashed_centre else yellow
    for road in town.roads:
        c = np.asarray(road.centreline, float)
        length = _length(c)
        ja, jb = road.a in junction_ids, road.b in junction_ids
        s0 = LINES_FROM if ja else 1.0
        s1 = length - (LINES_FROM if jb else 1.0)
        if s1 - s0 > 0.5:
            # centre line: solid (yellow) or dashed (white towns)
            if dashed_centre:
                k0 = s0
                while k0 < s1:
                    seg = _offset_line(c, k0, min(k0 + DASH, s1), 0.0)
                    cv2.polylines(centre_mask, [base_px(seg)], False, 255, 2, cv2.LINE_AA, 4)
                    k0 += DASH + DASH_GAP
            else:
                cv2.polylines(centre_mask, [base_px(_offset_line(c, s0, s1, 0.0))], False, 255, 2,
                              cv2.LINE_AA, 4)
            for side in (-1.0, 1.0):  # solid edge lines
                cv2.polylines(white, [base_px(_offset_line(c, s0, s1, side * (lw - 0.3)))], False, 255, 2,
                              cv2.LINE_AA, 4)
        # zebra crossings and stop lines where the road meets a junction
        for at_b, is_j in ((False, ja), (True, jb)):
            if not is_j or length < STOP[1] + 1.0:
                continue
            e = (lambda d: length - d) if at_b else (lambda d: d)
            # incoming lane: right of a->b at b's end, left of a->b (right of b->a) at a's end
            inc = -1.0 if at_b else 1.0
            o = -lw + 0.35
            while o + STRIPE_W <= lw - 0.35 + 1e-6:
                q = _quad(c, *sorted((e(ZEBRA[0]), e(ZEBRA[1]))), o, o + STRIPE_W)
                cv2.fillConvexPoly(white, base_px(q), 255, cv2.LINE_AA, 4)
                o += STRIPE_W + STRIPE_GAP
            q = _quad(c, *sorted((e(STOP[0]), e(STOP[1]))), inc * 0.15, inc * (lw - 0.3))
            cv2.fillConvexPoly(white, base_px(q), 255, cv2.LINE_AA, 4)
    return yellow, white


def bake_base(town, res: float = RES) -> GroundBase:
    """Rasterise ``town``'s ground: terrain, sidewalks (with kerbs), roads, junctions, markings."""
    rng = np.random.default_rng(stable_seed("ground", town.name))
    xmin, ymin, xmax, ymax = town.bounds
    n = 2 ** (LEVELS - 1)
    w = int(math.ceil((xmax - xmin) / res / n)) * n
    h = int(math.ceil((ymax - ymin) / res / n)) * n
    base = GroundBase(x0=float(xmin), y1=float(ymax), res=res, albedo=None, wet_dark=None, wet_refl=None,
                      puddle=None, border=tuple(town.style.terrain))
    px = base.px
    lw, sw = float(town.lane_width), float(town.sidewalk_width)
    st = town.style

    # distance (m) to the nearest road centreline and to the nearest junction
    lines = np.full((h, w), 255, np.uint8)
    for r in town.roads:
        cv2.polylines(lines, [px(r.centreline)], False, 0, 1, cv2.LINE_8, 4)
    dc = cv2.distanceTransform(lines, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    dc *= res
    del lines
    jm = np.zeros((h, w), np.uint8)
    for j in town.junctions:
        cv2.fillPoly(jm, [px(j.polygon)], 255, cv2.LINE_AA, 4)
    dj = cv2.distanceTransform(np.where(jm > 127, 0, 255).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    dj *= res
    junc = jm.astype(np.float32) * (1 / 255)
    del jm

    def cover(edge):  # soft coverage of "inside" for a signed edge distance (m, positive inside)
        edge *= 1 / res
        edge += 0.5
        return np.clip(edge, 0.0, 1.0, out=edge)

    road = np.maximum(cover(lw - dc), junc)
    side = np.maximum(cover(lw + sw - dc), cover(sw - dj)) if sw > 0 else np.zeros_like(road)
    kerb = side * (1 - road) * cover(0.22 - np.minimum(dc - lw, dj))
    gutter = (1 - junc) * cover(dc - (lw - 0.28)) * road
    del dj

    bld = np.zeros((h, w), np.uint8)
    for b in town.buildings:
        cv2.fillPoly(bld, [px(b.footprint)], 255, cv2.LINE_AA, 4)

    big = fbm((h, w), 20.0 / res, rng, octaves=3)
    mid = smooth_noise((h, w), 0.6 / res, rng)
    fine = rng.standard_normal((h, w), dtype=np.float32)

    # per-texel modulation of each surface (2-D fields; colours are applied per channel below)
    dry = np.clip(smooth_noise((h, w), 6.0 / res, rng) * 1.2 - 0.3, 0, 1)  # drier, browner grass
    terr_mod = 1 + 0.10 * big + 0.07 * mid + 0.08 * fine
    # sidewalk: paving slabs on a world-aligned 1.2 m grid, a lighter kerb stone at the road edge
    gx = ((np.arange(w, dtype=np.float32) + 0.5) * res + base.x0) % 1.2 < res * 1.01
    gy = (base.y1 - (np.arange(h, dtype=np.float32) + 0.5) * res) % 1.2 < res * 1.01
    joint = (gx[None, :] | gy[:, None]).astype(np.float32)
    side_mod = 1 + 0.05 * big + 0.04 * mid + 0.04 * fine - 0.12 * joint
    del joint
    # road: asphalt with wear, darker wheel tracks in each lane, repaired patches, a dark gutter
    track = np.abs(dc - lw / 2)
    track -= 0.85
    track *= 1 / 0.32
    track = np.exp(-track * track) * (1 - junc)
    patch = np.clip((smooth_noise((h, w), 2.5 / res, rng) - 1.0) * 4.0, 0, 1)
    road_mod = 1 + 0.06 * big + 0.05 * mid + 0.09 * fine - 0.08 * track - 0.07 * patch - 0.18 * gutter
    del patch, big
    yellow, white = _draw_markings(town, px, (h, w))
    wear = np.clip(0.9 + 0.1 * mid - 0.05 * fine, 0, 1) * road
    m_yel = yellow.astype(np.float32) * (1 / 255) * wear
    m_whi = white.astype(np.float32) * (1 / 255) * wear
    del yellow, white, wear
    mark = np.maximum(m_yel, m_whi)
    mark_mod = 1 + 0.03 * fine
    # contact shadow (ambient occlusion) around building footprints, dark ground under them
    b = bld.astype(np.float32) * (1 / 255)
    small = cv2.resize(b, (w // 4, h // 4), interpolation=cv2.INTER_AREA)
    ao = cv2.resize(cv2.GaussianBlur(small, (0, 0), 1.2 / res / 4), (w, h), interpolation=cv2.INTER_LINEAR)
    occl = (1 - 0.45 * ao * (1 - b)) * (1 - 0.6 * b)
    del ao, small, bld

    st_col = lambda c: np.asarray(c, np.float32) / 255  # noqa: E731
    terr, side_col, road_col = st_col(st.terrain), st_col(st.sidewalk), st_col(st.road)
    kerb_col = np.minimum(side_col * 1.15 + 0.05, 1.0)
    dry_col = terr * np.array([1.25, 1.05, 0.75], np.float32)
    albedo = np.empty((h, w, 3), np.uint8)
    for k in range(3):
        a = terr[k] * terr_mod
        a += 0.35 * dry * (dry_col[k] - a)
        sd = side_col[k] * side_mod
        sd += kerb * (kerb_col[k] - sd)
        sd -= a
        sd *= side
        a += sd
        rd = road_col[k] * road_mod
        rd -= a
        rd *= road
        a += rd
        for m, col in ((m_yel, st_col(st.centre_line)), (m_whi, st_col(st.marking))):
            mk = col[k] * mark_mod
            mk -= a
            mk *= m
            a += mk
        a *= occl
        a *= 255
        a += 0.5
        np.clip(a, 0, 255, out=a)
        albedo[..., k] = a
    del terr_mod, side_mod, road_mod, rd, sd, a, occl

    # wet response per texel, by class
    terrain_w = 1 - np.maximum(side, road)
    side_w = side * (1 - road)
    road_w = road * (1 - mark)
    wet_dark = (_WET_DARK[_TERRAIN] * terrain_w + _WET_DARK[_SIDEWALK] * side_w + _WET_DARK[_ROAD] * road_w
                + _WET_DARK[_MARK] * mark)
    wet_refl = (_WET_REFL[_TERRAIN] * terrain_w + _WET_REFL[_SIDEWALK] * side_w + _WET_REFL[_ROAD] * road_w
                + _WET_REFL[_MARK] * mark)
    # puddles: low spots on the road, along the gutters and in the wheel tracks
    low = smooth_noise((h, w), 3.0 / res, rng) + 0.6 * smooth_noise((h, w), 0.8 / res, rng)
    puddle = np.clip(low * 0.9 + 1.2 * gutter + 0.5 * track - 0.2, 0, 1) * road
    puddle += np.clip(low - 0.6, 0, 1) * side_w * 0.6

    base.albedo = albedo
    base.wet_dark = np.clip(wet_dark * 255 + 0.5, 0, 255).astype(np.uint8)
    base.wet_refl = np.clip(wet_refl * 255 + 0.5, 0, 255).astype(np.uint8)
    base.puddle = np.clip(puddle * 255 + 0.5, 0, 255).astype(np.uint8)
    return base


def _shadow_mask(town, base: GroundBase, weather: Weather) -> np.ndarray:
    """(H, W) float32 in 0-1: where buildings, trees and poles block the sun."""
    h, w = base.shape
    mask = np.zeros((h, w), np.uint8)
    el = math.radians(weather.sun_elevation)
    if el <= 0:
        return mask.astype(np.float32)
    away = -np.array([math.cos(math.radians(weather.sun_azimuth)), math.sin(math.radians(weather.sun_azimuth))])
    per_m = 1 / math.tan(el)  # shadow length per metre of height
    cap = 90.0
    for b in town.buildings:
        fp = np.asarray(b.footprint, float)
        off = away * min(b.height * per_m, cap)
        hull = cv2.convexHull(np.vstack([base.px(fp), base.px(fp + off)]))
        cv2.fillConvexPoly(mask, hull, 255, cv2.LINE_AA, 4)
    r_px = 1 / base.res
    for p in town.props:
        pos = np.asarray(p.position, float)
        if p.kind == "tree":
            trunk_top = max(p.height - 1.6 * p.radius, 0.5)
            a, t = base.px(np.array([pos, pos + away * min(trunk_top * per_m, cap)]))
            cv2.line(mask, tuple(a), tuple(t), 255, max(int(0.3 * r_px), 1), cv2.LINE_AA, 4)
            cen = base.px((pos + away * min((p.height - p.radius) * per_m, cap))[None])[0]
            stretch = min(1 / max(math.sin(el), 1e-3), 4.0)
            ang = math.degrees(math.atan2(-away[1], away[0]))  # texture rows run south
            axes = (int(p.radius * stretch * r_px * 16), int(p.radius * r_px * 16))
            cv2.ellipse(mask, tuple(int(v) for v in cen), axes, ang, 0, 360, 200, -1, cv2.LINE_AA, 4)
        else:
            a, t = base.px(np.array([pos, pos + away * min(p.height * per_m, cap)]))
            cv2.line(mask, tuple(a), tuple(t), 255, max(int(2 * p.radius * r_px), 1), cv2.LINE_AA, 4)
    m = mask.astype(np.float32) * (1 / 255)
    soft = weather.shadow_softness / base.res
    if soft >= 0.5:
        m = cv2.GaussianBlur(m, (0, 0), soft)
    return m


def bake_ground(town, weather: Weather, base: GroundBase | None = None) -> GroundTexture:
    """Light ``town``'s ground under ``weather`` and build its RGBA mip pyramid."""
    base = base or ground_base(town)
    sun_up = max(math.sin(math.radians(weather.sun_elevation)), 0.0)
    direct = np.asarray(weather.sun, np.float32) * sun_up
    ambient = np.asarray(weather.ambient, np.float32)
    sunlit = 1 - _shadow_mask(town, base, weather)  # (H, W): 1 in the sun, 0 in full shadow
    wet = weather.wetness
    # albedo scale: wet darkening and puddles (2-D; colours are applied per channel below)
    scale = base.wet_dark.astype(np.float32)
    scale *= -wet / 255
    scale += 1
    if weather.puddles > 0 and wet > 0:
        pud = base.puddle.astype(np.float32)
        pud *= 3.0 / 255
        pud -= 3.0 * (1 - weather.puddles)
        np.clip(pud, 0, 1, out=pud)
        pud *= wet
        scale -= 0.25 * pud
    else:
        pud = None
    scale *= 1 / 255
    rgba = np.empty(base.shape + (4,), np.uint8)
    chans = []
    for k in range(3):  # colour = albedo * (ambient + direct * sunlit)
        c = base.albedo[..., k].astype(np.float32)
        c *= scale
        light = sunlit * float(direct[k])
        light += float(ambient[k])
        c *= light
        chans.append(c)
    del light, sunlit, scale
    if weather.saturation != 1.0:
        grey = (chans[0] + chans[1] + chans[2]) * (1 / 3)
        for c in chans:
            c -= grey
            c *= weather.saturation
            c += grey
        del grey
    for k, c in enumerate(chans):
        c *= 255
        c += 0.5
        np.clip(c, 0, 255, out=c)
        rgba[..., k] = c
    del chans
    refl = base.wet_refl.astype(np.float32)
    refl *= wet
    if pud is not None:
        refl += 255 * pud
    refl += 0.5
    np.clip(refl, 0, 255, out=refl)
    rgba[..., 3] = refl
    del refl, pud
    border_rgb = np.asarray(town.style.terrain, np.float32) / 255 * np.asarray(weather.ambient, np.float32) + \
        np.asarray(town.style.terrain, np.float32) / 255 * direct
    border = tuple(float(v) for v in np.clip(border_rgb * 255, 0, 255)) + (0.0,)
    pyr = [rgba]
    for _ in range(LEVELS - 1):
        p = pyr[-1]
        pyr.append(cv2.resize(p, (p.shape[1] // 2, p.shape[0] // 2), interpolation=cv2.INTER_AREA))
    return GroundTexture(base=base, pyramid=pyr, borders=[border] * LEVELS)
