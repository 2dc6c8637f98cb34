"""What stands on the ground: building walls and props (trees, poles), and, per step, the items in
view in painter's order (far to near), computed once for all cameras (they share the optical
centre, so culling, back-face and occlusion tests, ordering and surface planes are shared).

Every item is a planar polygon (a wall, or a billboard facing the camera for trunks, canopies,
poles) with up to ``P`` vertices, plus a column of the surface table: its plane in the
camera-centred frame (normal, offset), where its texture starts along the surface, and its atlas
tile (which already holds its light). The renderer turns an id buffer into per-pixel depth, texture
coordinates and colour from that table. Walls are precomputed in world coordinates, so a step only
rotates and shifts them.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cicfw.sim.render.atlas import PPM, TILE_TOP, Atlas
from cicfw.sim.render.camera import MOUNT_HEIGHT
from cicfw.sim.render.noise import stable_seed
from cicfw.sim.render.weather import Weather
from cicfw.sim.town.geometry import polygon_area

P = 8  # vertices per item polygon (quads repeat their last vertex)
FAR_BUILDINGS = 200.0  # m; also at most 4 fog distances (farther walls are fog-coloured anyway)
FAR_PROPS = 80.0  # m; trees beyond are a few pixels
FAR_POLES = 50.0  # m; a pole beyond is less than a pixel wide (its lamp plate about one)
LOD_DIST = 45.0  # m; walls farther than this use the blurred facade tile
N_OCCLUDERS = 16  # nearest walls tested as occluders of everything else
TABLE = ("nx", "ny", "c", "s0", "y0")  # surface table rows (the along-surface axis is (-ny, nx))
NX, NY, C, S0, Y0 = range(len(TABLE))
_Y_TOP = (TILE_TOP - MOUNT_HEIGHT) * PPM  # atlas rows from a tile's top to camera height


@dataclass
class Items:
    """Items in view, in draw order: polygons (P, N, 3), vertex-major, in the camera-centred local
    frame (x forward, y left, z up, origin at the optical centre), vertex counts (N,), and the surface
    table (len(TABLE), N + 1) whose column 0 is the background."""

    poly: np.ndarray
    nv: np.ndarray
    table: np.ndarray

    def __len__(self) -> int:
        return self.poly.shape[1]


def _ccw(poly: np.ndarray) -> np.ndarray:
    return poly if polygon_area(poly) >= 0 else poly[::-1]


class Scene:
    """Walls and props of a town, lit for one weather."""

    def __init__(self, town, weather: Weather, atlas: Atlas) -> None:
        rng = np.random.default_rng(stable_seed("scene", town.name))
        p0, p1, h, soff, fac = [], [], [], [], []
        for b in town.buildings:
            fp = _ccw(np.asarray(b.footprint, float))
            s = float(rng.uniform(0, 6.0))
            for k in range(len(fp)):
                a, c = fp[k], fp[(k + 1) % len(fp)]
                length = float(np.linalg.norm(c - a))
                if length < 1e-6:
                    continue
                p0 += [a]
                p1 += [c]
                h += [float(b.height)]
                soff += [s]
                fac += [int(b.facade)]
                s += length
        self.w_p0 = np.array(p0, float).reshape(-1, 2)
        self.w_p1 = np.array(p1, float).reshape(-1, 2)
        self.w_h = np.array(h, float)
        d = self.w_p1 - self.w_p0
        t = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
        self.w_n = np.stack([t[:, 1], -t[:, 0]], 1)  # outward for CCW footprints
        self.w_t = t  # = (-n_y, n_x)
        self.w_c = (self.w_n * self.w_p0).sum(1)  # plane: n . X = c
        self.w_s = (np.array(soff) - (t * self.w_p0).sum(1)) * PPM - 0.5  # texture column = PPM t.X + w_s
        cos_sun = np.clip(self.w_n @ weather.sun_direction[:2], 0, 1)
        self.w_y0 = np.array([atlas.row0(atlas.facade(f, q)) for f, q in zip(fac, cos_sun)]) + _Y_TOP
        self.w_y0_far = np.array([atlas.row0(atlas.facade(f, q, far=True)) for f, q in zip(fac, cos_sun)]) + _Y_TOP
        self.w_top = self.w_h - MOUNT_HEIGHT

        props = list(town.props)
        self.p_pos = np.array([p.position for p in props], float).reshape(-1, 2)
        self.p_h = np.array([p.height for p in props], float)
        self.p_r = np.array([p.radius for p in props], float)
        tree = np.array([p.kind == "tree" for p in props], bool)
        self.p_soff = (rng.uniform(0, 6.0, len(props)) * PPM - 0.5).astype(np.float32)
        # billboard templates (along-axis offset, height relative to the camera) of each prop's two
        # items: trunk + canopy (a jittered octagon) for trees, pole + lamp plate for poles
        r, h = self.p_r[:, None], self.p_h[:, None]
        ang = 2 * np.pi * (np.arange(P) + 0.5) / P
        ca, sa = np.cos(ang)[None, :], np.sin(ang)[None, :]
        quad_s = np.array([1.0, -1.0, -1.0] + [1.0] * (P - 3))[None, :]  # left, right, right, left...
        quad_z = np.array([0.0, 0.0] + [1.0] * (P - 2))[None, :]  # bottom, bottom, top...
        half = np.where(tree[:, None], 0.12 + 0.05 * r, np.maximum(r, 0.06))
        z1 = np.where(tree[:, None], np.maximum(h - 1.5 * r, 0.8), h)
        jit = rng.uniform(0.88, 1.1, (len(props), P))
        tpl = np.empty((len(props), 2, P, 2))
        tpl[:, 0, :, 0] = quad_s * half
        tpl[:, 0, :, 1] = quad_z * z1
        tpl[:, 1, :, 0] = np.where(tree[:, None], ca * r * jit, np.sign(ca) * 0.35)
        tpl[:, 1, :, 1] = np.where(tree[:, None], h - r + sa * r * jit * 1.1, h - 0.35 * (sa < 0))
        tpl[..., 1] -= MOUNT_HEIGHT
        self.p_tpl = np.ascontiguousarray(tpl.transpose(2, 1, 0, 3))  # (P, 2 items, props, 2)
        y0 = {k: atlas.row0(getattr(atlas, k)) + _Y_TOP for k in ("foliage", "bark", "pole", "lamp")}
        self.p_y0 = np.stack([np.where(tree, y0["bark"], y0["pole"]), np.where(tree, y0["foliage"], y0["lamp"])],
                             1).astype(np.float32)
        self.p_top = self.p_h - MOUNT_HEIGHT
        self.far = min(FAR_BUILDINGS, 4.0 * weather.fog_distance)
        self.far_props = min(FAR_PROPS, 3.0 * weather.fog_distance)
        self.p_far = np.where(tree, self.far_props, min(FAR_POLES, self.far_props))
        self.w_p01 = np.stack([self.w_p0, self.w_p1], 1)  # (Nw, 2, 2)
        self.w_len2 = np.maximum((d * d).sum(1), 1e-9)

    # ------------------------------------------------------------------------------------------
    def items(self, cx: float, cy: float, yaw: float, az_lo: float, az_hi: float) -> Items:
        """Items seen from optical centre (cx, cy) (world) with heading ``yaw``, within local azimuths
        [az_lo, az_hi] (rad, CCW from the heading), in draw order."""
        c, s = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, -s], [s, c]])  # world offset (row vector) @ rot -> local (x fwd, y left)
        cxy = np.array([cx, cy])

        # walls facing the camera, near enough, inside the azimuth range; per-wall values are kept as
        # columns of one array F so that each selection is one gather:
        # F = [ax, ay, bx, by (ends, local), wd (nearest distance), lo, hi (azimuth span), wrap, index]
        side = self.w_c - self.w_n @ cxy  # n . (p0 - C) < 0: the camera is in front of the wall
        wi = np.flatnonzero(side < 0)
        F = np.empty((len(wi), 9))
        F[:, :4] = ((self.w_p01[wi] - cxy).reshape(-1, 2) @ rot).reshape(-1, 4)
        ax, ay, bx, by = F[:, 0], F[:, 1], F[:, 2], F[:, 3]
        dx, dy = bx - ax, by - ay
        u = (ax * dx + ay * dy) / self.w_len2[wi]
        np.minimum(np.maximum(-u, 0, out=u), 1, out=u)
        F[:, 4] = np.hypot(ax + u * dx, ay + u * dy)
        a0, a1 = np.arctan2(ay, ax), np.arctan2(by, bx)
        np.minimum(a0, a1, out=F[:, 5])
        np.maximum(a0, a1, out=F[:, 6])
        F[:, 7] = F[:, 6] - F[:, 5] > np.pi  # passes behind the camera: covers every direction
        F[F[:, 7] > 0, 5:7] = (-np.pi, np.pi)
        F[:, 8] = wi
        F = F[(F[:, 4] < self.far) & (F[:, 6] >= az_lo) & (F[:, 5] <= az_hi)]
        wi = F[:, 8].astype(np.intp)
        a, b, wd, lo, hi = F[:, 0:2], F[:, 2:4], F[:, 4], F[:, 5], F[:, 6]
        n = self.w_n[wi] @ rot
        wc = -side[wi]  # -(n . (p0 - C)) = distance of the camera in front of the wall's plane
        top = self.w_top[wi]

        # props near enough and inside the azimuth range
        pl = (self.p_pos - cxy) @ rot
        pd = np.hypot(pl[:, 0], pl[:, 1])
        paz = np.arctan2(pl[:, 1], pl[:, 0])
        pw = np.arctan2(self.p_r + 0.3, pd)
        pk = np.flatnonzero((pd < self.p_far) & (pd > 0.5) & (paz + pw >= az_lo) & (paz - pw <= az_hi))
        pl, pd, paz, pw = pl[pk], pd[pk], paz[pk], pw[pk]

        # occlusion: drop walls and props entirely hidden behind one of the nearest tall walls
        # (inside its azimuth span, behind its plane, below its lowest top edge)
        if len(wi) > 1:
            cand = np.flatnonzero((F[:, 7] == 0) & (top > 0))
            occ = cand[np.argsort(wd[cand])[:N_OCCLUDERS]]
            if len(occ):
                o_n, o_c = n[occ], -wc[occ]  # plane n . X = o_c (local, camera at the origin)
                fo = F[occ]
                o_top = top[occ] / np.sqrt(np.maximum(fo[:, 0] ** 2 + fo[:, 1] ** 2, fo[:, 2] ** 2 + fo[:, 3] ** 2))
                o_lo, o_hi = fo[None, :, 5], fo[None, :, 6]
                back = np.maximum(a @ o_n.T, b @ o_n.T) < o_c - 0.05  # both ends behind (N, occ)
                back &= o_lo <= lo[:, None]
                back &= o_hi >= hi[:, None]
                back &= o_top >= (top / np.maximum(wd, 0.1))[:, None]
                hid = back.any(1)
                hid[occ] = False
                vis = np.flatnonzero(~hid)
                F, n, wc = F[vis], n[vis], wc[vis]
                wi = F[:, 8].astype(np.intp)
                a, b, wd, lo, hi = F[:, 0:2], F[:, 2:4], F[:, 4], F[:, 5], F[:, 6]
                if len(pk):
                    pr = self.p_r[pk]
                    back = (pl @ o_n.T) < o_c - (pr + 0.05)[:, None]
                    back &= o_lo <= (paz - pw)[:, None]
                    back &= o_hi >= (paz + pw)[:, None]
                    back &= o_top >= (self.p_top[pk] / np.maximum(pd - pr, 0.1))[:, None]
                    vis = np.flatnonzero(~back.any(1))
                    pk, pl, pd, paz, pw = pk[vis], pl[vis], pd[vis], paz[vis], pw[vis]
        nw, m = len(wi), len(pk)
        n_items = nw + 2 * m

        # painter's order: walls by nearest distance, far first; each prop right after the last wall
        # it stands in front of (overlapping in azimuth); nearer props later
        keys = np.empty(n_items)
        keys[np.argsort(-wd, kind="stable")] = np.arange(nw)
        if m:
            if nw:
                over = lo[None, :] <= (paz + pw)[:, None]
                over &= hi[None, :] >= (paz - pw)[:, None]
                over &= (pl @ n.T) > -wc[None, :]  # and the prop stands in front of the wall
                after = np.where(over, keys[None, :nw], -1.0).max(1)
            else:
                after = np.full(m, -1.0)
            # exact ties (e.g. poles facing each other across the road) are broken by the prop's rank,
            # and a prop's upper item (canopy, lamp) follows its lower one (trunk, pole) directly
            pkey = after + (0.95 - 0.45 / (self.far_props + 1) * pd) + 1e-6 * np.arange(m)
            keys[nw:nw + m] = pkey
            keys[nw + m:] = pkey + 1e-7

        poly = np.empty((P, n_items, 3))  # vertex-major
        nv = np.full(n_items, 4, np.int32)
        tab = np.zeros((len(TABLE), n_items + 1), np.float32)
        tab[NX, 0] = 1.0  # background: depth 0
        # walls: (a, 0), (b, 0), (b, top), (a, top), (a, top)...
        poly[0, :nw, :2] = a
        poly[1:3, :nw, :2] = b
        poly[3:, :nw, :2] = a
        poly[:2, :nw, 2] = -MOUNT_HEIGHT
        poly[2:, :nw, 2] = self.w_top[wi]
        cols = slice(1, nw + 1)
        tab[NX:NY + 1, cols] = n.T
        tab[C, cols] = -wc
        tab[S0, cols] = self.w_s[wi] + PPM * (self.w_t[wi] @ cxy)
        tab[Y0, cols] = np.where(wd > LOD_DIST, self.w_y0_far[wi], self.w_y0[wi])
        if m:
            # billboards facing the camera: along-axis (-n_y, n_x) points to the right
            ux, uy = pl[:, 0] / pd, pl[:, 1] / pd
            tpl = self.p_tpl[:, :, pk]  # (P, 2, m, 2): along-axis offset, height
            poly[:, nw:, 0] = (pl[:, 0] + tpl[..., 0] * uy).reshape(P, 2 * m)
            poly[:, nw:, 1] = (pl[:, 1] - tpl[..., 0] * ux).reshape(P, 2 * m)
            poly[:, nw:, 2] = tpl[..., 1].reshape(P, 2 * m)
            nv[nw + m:] = P
            bb = tab[:, nw + 1:].reshape(len(TABLE), 2, m)  # (rows, lower/upper item, prop)
            bb[NX], bb[NY], bb[C], bb[S0] = -ux, -uy, -pd, self.p_soff[pk]
            bb[Y0] = self.p_y0[pk].T
        order = np.argsort(keys, kind="stable")
        tab[:, 1:] = tab[:, 1:][:, order]
        return Items(poly=poly[:, order], nv=nv[order], table=tab)
