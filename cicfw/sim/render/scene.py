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

P = 8  # vertices per item polygon (quads repeat their last vertex)
FAR_BUILDINGS = 200.0  # m; also at most 4 fog distances (farther walls are fog-coloured anyway)
FAR_PROPS = 80.0  # m; trees and poles beyond are a pixel or two
LOD_DIST = 45.0  # m; walls farther than this use the blurred facade tile
N_OCCLUDERS = 16  # nearest walls tested as occluders of everything else
TABLE = ("nx", "ny", "c", "s0", "y0")  # surface table rows (the along-surface axis is (-ny, nx))
NX, NY, C, S0, Y0 = range(len(TABLE))
_Y_TOP = (TILE_TOP - MOUNT_HEIGHT) * PPM  # atlas rows from a tile's top to camera height


@dataclass
class Items:
    """Items in view, in draw order: polygons (N, P, 3) in the camera-centred local frame (x forward,
    y left, z up, origin at the optical centre), vertex counts (N,), and the surface table
    (len(TABLE), N + 1) whose column 0 is the background."""

    poly: np.ndarray
    nv: np.ndarray
    table: np.ndarray

    def __len__(self) -> int:
        return len(self.poly)


def _ccw(poly: np.ndarray) -> np.ndarray:
    x, y = poly[:, 0], poly[:, 1]
    area = 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    return poly if area >= 0 else poly[::-1]


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
        self.p_tpl = tpl
        y0 = {k: atlas.row0(getattr(atlas, k)) + _Y_TOP for k in ("foliage", "bark", "pole", "lamp")}
        self.p_y0 = np.stack([np.where(tree, y0["bark"], y0["pole"]), np.where(tree, y0["foliage"], y0["lamp"])],
                             1).astype(np.float32)
        self.p_top = self.p_h - MOUNT_HEIGHT
        self.far = min(FAR_BUILDINGS, 4.0 * weather.fog_distance)
        self.far_props = min(FAR_PROPS, 3.0 * weather.fog_distance)
        self.w_p01 = np.stack([self.w_p0, self.w_p1], 1)  # (Nw, 2, 2)

    # ------------------------------------------------------------------------------------------
    def items(self, cx: float, cy: float, yaw: float, az_lo: float, az_hi: float) -> Items:
        """Items seen from optical centre (cx, cy) (world) with heading ``yaw``, within local azimuths
        [az_lo, az_hi] (rad, CCW from the heading), in draw order."""
        c, s = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, -s], [s, c]])  # world offset (row vector) @ rot -> local (x fwd, y left)
        cxy = np.array([cx, cy])

        # walls facing the camera, near enough, inside the azimuth range
        side = self.w_c - self.w_n @ cxy  # n . (p0 - C) < 0: the camera is in front of the wall
        wi = np.nonzero(side < 0)[0]
        ab = (self.w_p01[wi] - cxy) @ rot  # (N, 2, 2) wall ends, local
        a, b = ab[:, 0], ab[:, 1]
        d = b - a
        u = np.clip(-np.einsum("ij,ij->i", a, d) / np.einsum("ij,ij->i", d, d), 0, 1)
        wd = np.hypot(*(a + u[:, None] * d).T)  # nearest distance of each wall
        ang = np.arctan2(ab[..., 1], ab[..., 0])
        lo, hi = ang.min(1), ang.max(1)
        wrap = hi - lo > np.pi  # passes behind the camera: treat as covering every direction
        lo[wrap], hi[wrap] = -np.pi, np.pi
        keep = np.nonzero((wd < self.far) & (hi >= az_lo) & (lo <= az_hi))[0]
        wi, a, b, wd, lo, hi, wrap = wi[keep], a[keep], b[keep], wd[keep], lo[keep], hi[keep], wrap[keep]
        n = self.w_n[wi] @ rot
        wc = -side[wi]  # -(n . (p0 - C)) = distance of the camera in front of the wall's plane
        top = self.w_top[wi]

        # props near enough and inside the azimuth range
        pl = (self.p_pos - cxy) @ rot
        pd = np.hypot(pl[:, 0], pl[:, 1])
        paz = np.arctan2(pl[:, 1], pl[:, 0])
        pw = np.arctan2(self.p_r + 0.3, pd)
        pk = np.nonzero((pd < self.far_props) & (pd > 0.5) & (paz + pw >= az_lo) & (paz - pw <= az_hi))[0]
        pl, pd, paz, pw = pl[pk], pd[pk], paz[pk], pw[pk]

        # occlusion: drop walls and props entirely hidden behind one of the nearest tall walls
        # (inside its azimuth span, behind its plane, below its lowest top edge)
        if len(wi) > 1:
            cand = np.nonzero(~wrap & (top > 0))[0]
            occ = cand[np.argsort(wd[cand])[:N_OCCLUDERS]]
            if len(occ):
                o_n, o_c = n[occ], -wc[occ]  # plane n . X = o_c (local, camera at the origin)
                o_top = top[occ] / np.sqrt(np.maximum((a[occ] ** 2).sum(1), (b[occ] ** 2).sum(1)))
                o_lo, o_hi = lo[occ, None], hi[occ, None]
                back = np.maximum(a @ o_n.T, b @ o_n.T) < o_c - 0.05  # both ends behind (N, occ)
                hid = ((o_lo.T <= lo[:, None]) & (o_hi.T >= hi[:, None]) & back
                       & (o_top >= (top / np.maximum(wd, 0.1))[:, None])).any(1)
                hid[occ] = False
                vis = np.nonzero(~hid)[0]
                wi, a, b, wd, lo, hi, n, wc = wi[vis], a[vis], b[vis], wd[vis], lo[vis], hi[vis], n[vis], wc[vis]
                if len(pk):
                    pr = self.p_r[pk]
                    back = (pl @ o_n.T) < o_c - (pr + 0.05)[:, None]
                    hid = ((o_lo.T <= (paz - pw)[:, None]) & (o_hi.T >= (paz + pw)[:, None]) & back
                           & (o_top >= (self.p_top[pk] / np.maximum(pd - pr, 0.1))[:, None])).any(1)
                    vis = np.nonzero(~hid)[0]
                    pk, pl, pd, paz, pw = pk[vis], pl[vis], pd[vis], paz[vis], pw[vis]
        nw, m = len(wi), len(pk)

        # painter's order: walls by nearest distance, far first; each prop right after the last wall
        # it stands in front of (overlapping in azimuth); nearer props later
        keys = np.empty(nw + 2 * m)
        keys[np.argsort(-wd, kind="stable")] = np.arange(nw)
        if m:
            if nw:
                over = (lo[None, :] <= (paz + pw)[:, None]) & (hi[None, :] >= (paz - pw)[:, None])
                infront = (pl @ n.T) > -wc[None, :]
                after = np.where(over & infront, keys[None, :nw], -1.0).max(1)
            else:
                after = np.full(m, -1.0)
            keys[nw:nw + m] = after + 0.5 + 0.45 * (1 - pd / (self.far_props + 1))
            keys[nw + m:] = keys[nw:nw + m] + 1e-4

        poly = np.empty((nw + 2 * m, P, 3))
        nv = np.full(nw + 2 * m, 4, np.int32)
        tab = np.zeros((len(TABLE), nw + 2 * m + 1), np.float32)
        tab[NX, 0] = 1.0  # background: depth 0
        # walls: (a, 0), (b, 0), (b, top), (a, top), (a, top)...
        poly[:nw, 0, :2], poly[:nw, 1:3, :2] = a, b[:, None, :]
        poly[:nw, 3:, :2] = a[:, None, :]
        poly[:nw, :2, 2] = -MOUNT_HEIGHT
        poly[:nw, 2:, 2] = self.w_top[wi][:, None]
        cols = slice(1, nw + 1)
        tab[NX, cols], tab[NY, cols] = n.T
        tab[C, cols] = -wc
        tab[S0, cols] = self.w_s[wi] + PPM * (self.w_t[wi] @ cxy)
        tab[Y0, cols] = np.where(wd > LOD_DIST, self.w_y0_far[wi], self.w_y0[wi])
        if m:
            # billboards facing the camera: along-axis (-n_y, n_x) points to the right
            ux, uy = pl[:, 0] / pd, pl[:, 1] / pd
            tpl = self.p_tpl[pk].transpose(1, 0, 2, 3)  # (2, m, P, 2)
            poly[nw:, :, 0] = (pl[None, :, None, 0] + tpl[..., 0] * uy[None, :, None]).reshape(2 * m, P)
            poly[nw:, :, 1] = (pl[None, :, None, 1] - tpl[..., 0] * ux[None, :, None]).reshape(2 * m, P)
            poly[nw:, :, 2] = tpl[..., 1].reshape(2 * m, P)
            nv[nw + m:] = P
            pc = slice(nw + 1, nw + 2 * m + 1)
            tab[NX, pc], tab[NY, pc] = np.tile(-ux, 2), np.tile(-uy, 2)
            tab[C, pc] = np.tile(-pd, 2)
            tab[S0, pc] = np.tile(self.p_soff[pk], 2)
            tab[Y0, pc] = self.p_y0[pk].T.ravel()
        order = np.argsort(keys, kind="stable")
        tab[:, 1:] = tab[:, 1:][:, order]
        return Items(poly=poly[order], nv=nv[order], table=tab)
