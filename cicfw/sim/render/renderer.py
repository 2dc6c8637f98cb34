"""``Renderer(town, weather, seed, cameras).render(x, y, yaw, t) -> {camera: (88, 200, 3) uint8 RGB}``.

Per step: the scene's items in view are culled, ordered and given surface planes once for all
cameras (they share the optical centre). Per camera: the ground is warped from the town texture
by homography (rows below the horizon only, one mip level per band of rows), the sky is looked up
in a world-fixed panorama, items are filled into an id buffer (one fill each), then depth, texture
coordinates and fog come out of one vectorised pass over that buffer (light is baked into the
atlas); wet roads blend in a rough mirror image, one fog pass covers the frame, rain slides down.
Everything that does not depend on the pose (pixel rays, ground distance and fog, mip bands,
Fresnel weights) is computed once per renderer.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from cicfw.core.errors import CicfwError
from cicfw.sim.render import camera as cam_mod
from cicfw.sim.render import ground
from cicfw.sim.render.atlas import PPM, TW, Atlas, build_atlas
from cicfw.sim.render.camera import (CAMERAS, CX, CY, FIRST_GROUND_ROW, FX, FY, HORIZON_ROW, IMAGE_H, IMAGE_W,
                                     MOUNT_FORWARD, MOUNT_HEIGHT, NEAR, Camera, get_camera)
from cicfw.sim.render.ground import LEVELS, GroundTexture, bake_ground, ground_base
from cicfw.sim.render.noise import smooth_noise, stable_seed
from cicfw.sim.render.scene import C, NX, NY, P, S0, TABLE, Y0, Items, Scene
from cicfw.sim.render.sky import heading_shift, pad_panorama, pano_maps, rain_streaks, sky_panorama
from cicfw.sim.render.weather import Weather, get_weather

MIN_BAND = 3  # rows per mip band at least
MAX_ITEMS = 255  # per camera (the id buffer is uint8); the farthest are dropped beyond
RAIN_SPEED = 700.0  # rain texture rows per second
V0 = FIRST_GROUND_ROW
NG = IMAGE_H - V0  # ground rows

_TEXTURES: dict = {}
_ROW_INDEX = np.repeat(np.arange(IMAGE_H, dtype=np.uint8)[:, None], IMAGE_W, axis=1)


def _ground_texture(town, weather: Weather) -> GroundTexture:
    """The baked ground of (town, weather), shared by every renderer of that pair."""
    key = (id(town), weather)
    hit = _TEXTURES.get(key)
    if hit is None or hit[0] is not town:
        hit = (town, bake_ground(town, weather, ground_base(town)))
        _TEXTURES[key] = hit
    return hit[1]


def clear_caches() -> None:
    """Forget baked ground textures (frees memory; the next Renderer bakes again)."""
    _TEXTURES.clear()
    ground._BASE_CACHE.clear()


class _CameraTables:
    """Pose-independent per-camera data."""

    def __init__(self, cam: Camera, rng: np.random.Generator) -> None:
        self.cam = cam
        self.rot_t = np.ascontiguousarray(cam.rotation.T)  # local row vectors @ rot_t -> camera
        self.kr_inv = np.linalg.inv(cam_mod.K @ cam.rotation)  # image -> local direction
        rays = cam_mod.pixel_rays(cam)
        dx, dy, dz = (np.ascontiguousarray(rays[..., k]) for k in range(3))
        dn = np.linalg.norm(rays, axis=-1).astype(np.float32)
        self.dx, self.dy = dx, dy
        self.dx_ppm, self.dy_ppm = dx * PPM, dy * PPM
        self.dz_ppm = (-dz * PPM).astype(np.float32)  # atlas rows per unit of depth
        self.dn = dn
        self.pano_x, self.pano_y = pano_maps(rays[:V0])
        gdz = rays[V0:, :, 2]
        self.ground_dist = (MOUNT_HEIGHT / -gdz * dn[V0:]).astype(np.float32)
        dep = np.arcsin(np.clip(-gdz / dn[V0:], 0, 1))  # depression angle, for the Fresnel weight
        self.fresnel8 = np.round(255 * (0.2 + 0.7 * (1 - np.sin(dep)) ** 4)).astype(np.uint8)
        # the mirror lookup of wet reflections at half resolution, jittered (a rough water film)
        hs, ws = (NG + 1) // 2, IMAGE_W // 2
        self.rough_x = np.clip(2 * np.arange(ws, dtype=np.float32)[None, :] + 0.5
                               + 1.0 * smooth_noise((hs, ws), 1.5, rng), 0, IMAGE_W - 1).astype(np.float32)
        self.rough_y = (V0 + 2 * np.arange(hs, dtype=np.float32)[:, None] + 0.5
                        - 2.0 * np.abs(smooth_noise((hs, ws), 1.2, rng))).astype(np.float32)
        az = np.arctan2(rays[..., 1], rays[..., 0])
        self.az_lo, self.az_hi = float(az.min()), float(az.max())


def mip_bands(levels: int, res: float) -> list[tuple[int, int, int]]:
    """(row0, row1, level) bands: the level whose texels match the ground footprint of each row
    (geometric mean of the along- and across-row footprints, centre column); pose independent on
    flat ground, the same for all three cameras."""
    dist = cam_mod.ground_distance_rows()
    bands: list[list[int]] = []
    for r in range(V0, IMAGE_H):
        d0 = dist[r]
        d1 = dist[r - 1] if r - 1 >= V0 else 2 * d0
        along = abs(d1 - d0)
        across = math.hypot(d0, MOUNT_HEIGHT) / FX * math.hypot(1, (r - CY) / FY)
        foot = math.sqrt(max(along, 1e-6) * across)
        lvl = int(np.clip(math.floor(math.log2(max(foot / res, 1.0)) + 0.5), 0, levels - 1))
        if bands and bands[-1][2] == lvl:
            bands[-1][1] = r + 1
        else:
            bands.append([r, r + 1, lvl])
    # merge bands thinner than MIN_BAND rows into the next one at the finer level (every warp call
    # costs a few microseconds; the thin bands are the far rows next to the horizon)
    merged: list[list[int]] = []
    for band in bands:
        if merged and merged[-1][1] - merged[-1][0] < MIN_BAND:
            merged[-1][1], merged[-1][2] = band[1], min(merged[-1][2], band[2])
        else:
            merged.append(list(band))
    return [tuple(b) for b in merged]


class Renderer:
    """Camera images of ``town`` under ``weather`` (a name from WEATHERS, or a Weather).

    ``render(x, y, yaw, t)`` takes the vehicle pose (rear axle, as cicfw.sim.vehicle; the cameras sit
    MOUNT_FORWARD m ahead of it) and returns {camera name: (88, 200, 3) uint8 RGB}. The same seed,
    pose and t give the same bytes; t (seconds) animates the rain.
    """

    def __init__(self, town, weather: str | Weather, seed: int = 0,
                 cameras: tuple[str, ...] | list[str] = ("centre", "left", "right")) -> None:
        self.town = town
        self.weather = weather if isinstance(weather, Weather) else get_weather(weather)
        cams = (cameras,) if isinstance(cameras, str) else tuple(cameras)
        if not cams:
            raise CicfwError(f"Renderer needs at least one camera; known cameras: {', '.join(CAMERAS)}")
        self.cameras = tuple(get_camera(c).name for c in cams)
        self.seed = int(seed)
        w = self.weather

        self.ground = _ground_texture(town, w)
        self.atlas: Atlas = build_atlas(town.style, w)
        self.scene = Scene(town, w, self.atlas)
        # each camera's tables from its own seed: its images do not depend on the other cameras
        self.tables = {c: _CameraTables(get_camera(c), np.random.default_rng(stable_seed("camera", self.seed, w.name, c)))
                       for c in self.cameras}
        self._rot_all = np.concatenate([t.rot_t for t in self.tables.values()], axis=1)  # (3, 3 * cams)
        self.az_lo = min(t.az_lo for t in self.tables.values())
        self.az_hi = max(t.az_hi for t in self.tables.values())
        self.bands = mip_bands(LEVELS, self.ground.base.res)
        w2t = self.ground.base.world_to_texel()
        lvl = [np.array([[2.0 ** -k, 0, 0.5 * 2.0 ** -k - 0.5], [0, 2.0 ** -k, 0.5 * 2.0 ** -k - 0.5],
                         [0, 0, 1.0]]) @ w2t for k in range(LEVELS)]
        self._band_pre = np.stack([lvl[k] for _, _, k in self.bands])  # world -> texel of the band's level
        self._band_post = np.stack([np.array([[1.0, 0, 0], [0, 1.0, a], [0, 0, 1.0]]) for a, _, _ in self.bands])

        sky = sky_panorama(w, town.style.vegetation, stable_seed("sky", self.seed, w.name))
        sky4 = np.zeros(sky.shape[:2] + (4,), np.uint8)
        sky4[..., :3] = np.clip(sky * 255 + 0.5, 0, 255)
        self.sky = pad_panorama(sky4)
        fog = np.asarray(w.fog_colour, np.float64) * 255
        self._fog_img = np.zeros((IMAGE_H, IMAGE_W, 4), np.uint8)
        self._fog_img[..., :3] = np.round(fog)
        self.inv_fog = -1.0 / w.fog_distance
        # fog of the flat ground is pose independent; the sky gets none
        ct0 = next(iter(self.tables.values()))
        self.keep_fixed = np.ones((IMAGE_H, IMAGE_W), np.float32)
        self.keep_fixed[V0:] = np.exp(ct0.ground_dist * self.inv_fog)
        for ct in self.tables.values():
            ct.dn_fog = (ct.dn * self.inv_fog).astype(np.float32)
        self.wet = w.wetness > 0 or w.puddles > 0
        streaks = rain_streaks(w, stable_seed("rain", self.seed, w.name), IMAGE_H, IMAGE_W)
        self.rain = None
        if streaks is not None:
            self.rain = np.zeros(streaks.shape[:2] + (4,), np.uint8)
            self.rain[..., :3] = streaks

        self._ids = np.zeros((IMAGE_H, IMAGE_W), np.uint8)
        self._lut = np.zeros((len(TABLE), 256), np.float32)
        self.last_items: dict[str, int] = {}  # items drawn per camera in the last render (diagnostics)

    # ------------------------------------------------------------------------------------------
    def render(self, x: float, y: float, yaw: float, t: float = 0.0) -> dict[str, np.ndarray]:
        """Images of every camera for the vehicle pose (x, y, yaw) at time ``t`` (s, animates rain)."""
        x, y, yaw = float(x), float(y), float(yaw)
        cx, cy = x + MOUNT_FORWARD * math.cos(yaw), y + MOUNT_FORWARD * math.sin(yaw)
        items = self.scene.items(cx, cy, yaw, self.az_lo, self.az_hi)
        polys = self._project(items)
        minv = self._ground_inverse(x, y, yaw)
        shift = heading_shift(yaw)
        return {name: self._render_camera(self.tables[name], items, polys[k], minv, shift, t)
                for k, name in enumerate(self.cameras)}

    @staticmethod
    def _ground_inverse(x: float, y: float, yaw: float) -> np.ndarray:
        """Inverse of M, the map from world ground points (X, Y, 1) to camera-centred local points,
        M = [[c, s, -(c x + s y) - F], [-s, c, s x - c y], [0, 0, -H]] (image = K R_cam M)."""
        c, s = math.cos(yaw), math.sin(yaw)
        tx, ty = -(c * x + s * y) - MOUNT_FORWARD, s * x - c * y
        h = MOUNT_HEIGHT
        return np.array([[c, -s, (c * tx - s * ty) / h], [s, c, (s * tx + c * ty) / h], [0, 0, -1.0 / h]])

    def _project(self, items: Items) -> list[tuple[np.ndarray, list]]:
        """Project the items into every camera at once: per camera, the indices of the items in view
        (draw order, at most MAX_ITEMS: the nearest) and their image polygons (fixed point, shift 4)."""
        nc = len(self.cameras)
        n = len(items)
        if n == 0:
            return [(np.zeros(0, np.intp), [])] * nc
        pc = (items.poly @ self._rot_all).reshape(P, n, nc, 3)  # (vertex, item, camera, xyz)
        z = pc[..., 2]
        rz = 1.0 / np.maximum(z, NEAR)
        u = pc[..., 0] * rz
        u *= FX
        u += CX
        v = pc[..., 1] * rz
        v *= FY
        v += CY
        inside = z.max(0) > NEAR  # (N, cams); reductions over the leading (vertex) axis are cheap
        inside &= u.max(0) >= -0.5
        inside &= u.min(0) <= IMAGE_W - 0.5
        inside &= v.max(0) >= -0.5
        inside &= v.min(0) <= IMAGE_H - 0.5
        part = z.min(0) <= NEAR  # crossing the near plane: (u, v) above are wrong there, clip exactly
        uv = np.stack([u, v], -1)
        uv *= 16
        np.clip(uv, -2 ** 24, 2 ** 24, out=uv)
        fixed = np.rint(uv).astype(np.int32)
        out = []
        for k in range(nc):
            idx = np.flatnonzero(inside[:, k])
            if len(idx) > MAX_ITEMS:
                idx = idx[-MAX_ITEMS:]  # keep the nearest (drawn last)
            polys = list(np.ascontiguousarray(fixed[:, idx, k].transpose(1, 0, 2)))
            for j in np.flatnonzero(part[idx, k]).tolist():
                i = idx[j]
                polys[j] = _clip_near(pc[:items.nv[i], i, k].tolist())
            out.append((idx, polys))
        return out

    def _draw_ids(self, ct: _CameraTables, idx: np.ndarray, polys: list) -> np.ndarray:
        """Fill the id buffer (1..n in draw order); returns the surface-table columns of ids 0..n."""
        ids = self._ids
        ids.fill(0)
        fill = cv2.fillConvexPoly
        for j, q in enumerate(polys, 1):
            if q is not None:
                fill(ids, q, j, cv2.LINE_8, 4)
        self.last_items[ct.cam.name] = len(idx)
        cols = np.empty(len(idx) + 1, np.intp)
        cols[0] = 0
        cols[1:] = idx + 1
        return cols

    def _render_camera(self, ct: _CameraTables, items: Items, proj: tuple, minv: np.ndarray, shift: float,
                       t: float) -> np.ndarray:
        frame = np.empty((IMAGE_H, IMAGE_W, 4), np.uint8)
        # sky: the world-fixed panorama, turned by the heading
        cv2.remap(self.sky, ct.pano_x + shift, ct.pano_y, cv2.INTER_LINEAR, dst=frame[:V0],
                  borderMode=cv2.BORDER_REPLICATE)
        # ground: image -> texture homography per band of rows, each from its mip level
        mats = self._band_pre @ (minv @ ct.kr_inv) @ self._band_post
        pyr, borders = self.ground.pyramid, self.ground.borders
        flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
        for (a, b, lvl), mat in zip(self.bands, mats):
            cv2.warpPerspective(pyr[lvl], mat, (IMAGE_W, b - a), dst=frame[a:b], flags=flags,
                                borderMode=cv2.BORDER_CONSTANT, borderValue=borders[lvl])

        # items: id buffer -> depth -> atlas lookup (lit) -> composited over sky and ground
        cols = self._draw_ids(ct, *proj)
        n = len(cols)
        keep = self.keep_fixed
        bx, by, bw, bh = cv2.boundingRect(self._ids) if n > 1 else (0, 0, 0, 0)
        if bw == 0:
            n = 1  # nothing in view covers a pixel
        else:  # the per-pixel pass runs over the items' bounding box only
            box = (slice(by, by + bh), slice(bx, bx + bw))
            ids = self._ids[box]
            lut = self._lut
            lut[:, :n] = items.table[:, cols]
            lut[:, n:] = 0
            LUT = cv2.LUT
            nx, ny = LUT(ids, lut[NX]), LUT(ids, lut[NY])
            den = nx * ct.dx[box]
            den += ny * ct.dy[box]
            dep = LUT(ids, lut[C])
            dep /= den  # ray parameter: distance / |ray|
            sx = nx * ct.dy_ppm[box]
            sx -= ny * ct.dx_ppm[box]
            sx *= dep
            sx += LUT(ids, lut[S0])
            wrap = sx * (1 / TW)  # the tile repeats along the surface: sx mod TW
            np.floor(wrap, out=wrap)
            wrap *= TW
            sx -= wrap
            sy = dep * ct.dz_ppm[box]
            sy += LUT(ids, lut[Y0])
            alb = cv2.remap(self.atlas.image, sx, sy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
            # numpy, not cv2.compare: OpenCV reads a 1x1 array as a scalar and refuses the comparison
            mask = np.greater(ids, 0).view(np.uint8)
            cv2.copyTo(alb, mask, frame[box])
            dep *= ct.dn_fog[box]
            keep = self.keep_fixed.copy()
            cv2.copyTo(cv2.exp(dep), mask, keep[box])
        # fog over everything, in 8 bits: out = frame * k + fog * (1 - k); on wet ground part of k goes
        # to a rough mirror image instead: frame * (k - kw) + mirror * kw
        k8 = cv2.convertScaleAbs(keep, alpha=255.0)
        fog_term = cv2.multiply(self._fog_img, cv2.bitwise_not(cv2.merge([k8, k8, k8, k8])), scale=1 / 255)
        if self.wet:
            refl, w8 = self._reflection(ct, frame, n > 1)
            kw = cv2.multiply(k8[V0:], w8, scale=1 / 255)
            k8[V0:] -= kw
            fog_term[V0:] += cv2.multiply(refl, cv2.merge([kw, kw, kw, kw]), scale=1 / 255)
        out = cv2.multiply(frame, cv2.merge([k8, k8, k8, k8]), scale=1 / 255)
        out += fog_term
        if self.rain is not None:
            th = self.rain.shape[0]
            off = (int(t * RAIN_SPEED) + 97 * ct.cam.cam_id + 31 * self.seed) % (th - IMAGE_H)
            cv2.add(out, self.rain[off:off + IMAGE_H], dst=out)
        return cv2.cvtColor(out, cv2.COLOR_RGBA2RGB)

    def _reflection(self, ct: _CameraTables, frame: np.ndarray, has_items: bool) -> tuple[np.ndarray, np.ndarray]:
        """A rough mirror image for the ground rows of ``frame`` (what stands above, mirrored about the
        base of the lowest item in each column, or the horizon; sampled at half resolution with a
        jitter and upsampled, so it is soft) and its weight: the ground's wetness (texture alpha, 0 on
        items) x a Fresnel term."""
        if has_items:  # lowest item row of each column (0 where none), at half resolution
            low = cv2.min(cv2.compare(self._ids, 0, cv2.CMP_GT), _ROW_INDEX).max(0)[None, 1::2]
            base = np.maximum(low.astype(np.float32) + 0.5, HORIZON_ROW)
        else:
            base = np.full((1, IMAGE_W // 2), HORIZON_ROW, np.float32)
        my = 2 * base - ct.rough_y
        np.maximum(my, 0, out=my)
        small = cv2.remap(frame, ct.rough_x, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
        refl = cv2.resize(small, (IMAGE_W, NG), interpolation=cv2.INTER_LINEAR)
        w8 = cv2.multiply(cv2.extractChannel(frame[V0:], 3), ct.fresnel8, scale=1 / 255)
        return refl, w8


def _clip_near(q: list) -> np.ndarray | None:
    """Clip a camera-space polygon (list of [x, y, z]) to z >= NEAR and project it (fixed point, shift 4)."""
    out = []
    m = len(q)
    for i in range(m):
        a, b = q[i], q[(i + 1) % m]
        ia, ib = a[2] >= NEAR, b[2] >= NEAR
        if ia:
            out.append(a)
        if ia != ib:
            f = (NEAR - a[2]) / (b[2] - a[2])
            out.append([a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), NEAR])
    if len(out) < 3:
        return None
    lim = 2.0 ** 24
    return np.array([[round(max(-lim, min(lim, (FX * x / z + CX) * 16))),
                      round(max(-lim, min(lim, (FY * y / z + CY) * 16)))] for x, y, z in out], np.int32)
