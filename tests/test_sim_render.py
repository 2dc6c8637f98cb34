"""The renderer on a tiny hand-made town: image format, determinism, rain, geometry, asymmetric markings.

The fixture town is one X junction at the origin with four straight arms (N, E, S, W) and, unless a
test says otherwise, no buildings and no props, so what a test adds is the only thing standing.
"""
import math

import numpy as np
import pytest

from cicfw.sim.render import CAMERAS, WEATHERS, Renderer, Weather
from cicfw.sim.render.weather import HARSH_WEATHERS
from cicfw.sim.render.camera import CX, HORIZON_ROW, MOUNT_FORWARD
from cicfw.sim.town import Building, Junction, Prop, Road, Style, Town

LW = 3.5
STYLE = Style(road=(90, 90, 94), marking=(235, 235, 230), centre_line=(228, 196, 60), sidewalk=(170, 166, 160),
              terrain=(96, 128, 70), facades=((166, 92, 70), (196, 170, 130)), roof=(70, 60, 58),
              vegetation=(58, 104, 48), pole=(80, 80, 84), sky=(150, 190, 235))
# a calm grey weather: no sun (no shadows), no rain, no fog to speak of
FLAT = Weather("Flat", sun_elevation=60, sun_azimuth=0, sun=(0.0, 0.0, 0.0), ambient=(1.0, 1.0, 1.0),
               sky_zenith=(0.5, 0.6, 0.8), sky_horizon=(0.8, 0.85, 0.9), fog_distance=1e6)


def _line(p, q):
    n = int(np.ceil(np.linalg.norm(np.subtract(q, p)) / 0.5))
    return np.linspace(p, q, n + 1)


def tiny_town(buildings=(), props=()) -> Town:
    e = 10.0  # junction half size
    arms = {"n": ((0, e), (0, 60)), "e": ((e, 0), (60, 0)), "s": ((0, -60), (0, -e)), "w": ((-60, 0), (-e, 0))}
    roads = (Road("j-n", "j", "n", _line(*arms["n"])), Road("j-e", "j", "e", _line(*arms["e"])),
             Road("s-j", "s", "j", _line(*arms["s"])), Road("w-j", "w", "j", _line(*arms["w"])))
    poly = np.array([[-e, -LW], [-LW, -LW], [-LW, -e], [LW, -e], [LW, -LW], [e, -LW], [e, LW], [LW, LW],
                     [LW, e], [-LW, e], [-LW, LW], [-e, LW]], float)
    junction = Junction("j", np.zeros(2), poly, ("j-n", "j-e", "s-j", "w-j"), radius=e)
    return Town(name="tiny", lane_width=LW, sidewalk_width=2.0, roads=roads, junctions=(junction,),
                buildings=tuple(buildings), props=tuple(props), style=STYLE, bounds=(-70.0, -70.0, 70.0, 70.0))


def box(x0, y0, x1, y1, h=12.0, facade=0) -> Building:
    return Building(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float), h, facade)


NORTHBOUND = (LW / 2, -40.0, math.pi / 2)  # right lane of the southern arm, heading north


@pytest.fixture(scope="module")
def town():
    return tiny_town(buildings=[box(8, -50, 20, -38), box(-22, -45, -9, -30, 18, 1), box(9, 12, 25, 30, 8, 1)],
                     props=[Prop("tree", np.array([7.0, -25.0]), 6.0, 1.8), Prop("pole", np.array([-6.0, -20.0]), 7.0, 0.15)])


@pytest.fixture(scope="module")
def rainy(town):
    return Renderer(town, "MidRainyNoon", seed=3)


def test_images_are_uint8_88x200_rgb_for_every_camera(town, rainy):
    out = rainy.render(*NORTHBOUND, t=0.0)
    assert list(out) == ["centre", "left", "right"]
    for img in out.values():
        assert img.dtype == np.uint8 and img.shape == (88, 200, 3) and img.flags.c_contiguous
        assert img.std() > 5  # not a blank frame
    one = Renderer(town, "ClearNoon", cameras=("left",)).render(*NORTHBOUND)
    assert list(one) == ["left"] and one["left"].shape == (88, 200, 3)


def test_same_seed_same_bytes_and_rain_moves_with_time(town, rainy):
    a = rainy.render(*NORTHBOUND, t=1.0)
    b = Renderer(town, "MidRainyNoon", seed=3).render(*NORTHBOUND, t=1.0)  # a fresh renderer
    for cam in CAMERAS:
        assert np.array_equal(a[cam], b[cam])
    c = rainy.render(*NORTHBOUND, t=1.3)
    assert all(not np.array_equal(a[cam], c[cam]) for cam in CAMERAS)  # the streaks moved
    other = Renderer(town, "MidRainyNoon", seed=4).render(*NORTHBOUND, t=1.0)
    assert not np.array_equal(a["centre"], other["centre"])  # another seed, other rain
    dry = Renderer(town, "ClearNoon", seed=3, cameras=("centre",))
    assert np.array_equal(dry.render(*NORTHBOUND, t=0.0)["centre"], dry.render(*NORTHBOUND, t=5.0)["centre"])


def test_a_cameras_image_does_not_depend_on_the_other_cameras(town, rainy):
    both = rainy.render(*NORTHBOUND, t=0.7)
    for cam in ("left", "right"):
        alone = Renderer(town, "MidRainyNoon", seed=3, cameras=(cam,)).render(*NORTHBOUND, t=0.7)
        assert np.array_equal(alone[cam], both[cam])


def test_unknown_names_list_the_known_ones(town):
    with pytest.raises(ValueError) as e:
        Renderer(town, "Foggy")
    for name in WEATHERS:
        assert name in str(e.value)
    with pytest.raises(ValueError, match="known cameras: centre, left, right"):
        Renderer(town, "ClearNoon", cameras=("centre", "rear"))


def _yellow(img):
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > 120) & (g > 100) & (r - b > 110) & (g - b > 90)


def test_centre_line_is_on_the_drivers_left(town):
    """Right-hand traffic: in the right lane the yellow centre line is left of the image centre and the
    white edge line right of it. A mirrored world (or homography) puts them the other way round."""
    r = Renderer(town, FLAT, cameras=("centre",))
    for pose in (NORTHBOUND, (-LW / 2, 40.0, -math.pi / 2), (-40.0, -LW / 2, 0.0)):  # N-, S-, E-bound
        img = r.render(*pose)["centre"]
        ys, xs = np.nonzero(_yellow(img[28:]))  # the nearest ~14 m of road
        assert len(xs) > 40, pose
        assert np.all(xs < CX), pose
        grey = img.astype(int).sum(-1)
        near = grey[70:, :]  # the bottom rows: bright white edge line on the right only
        assert near[:, 120:].max() > near[:, :80].max() + 60, pose


def test_stop_line_crosses_only_the_incoming_lane(town):
    # ground texture: on the southern arm the stop line (northbound lane, x > 0) is at ~4 m from the
    # junction edge (y = -10 - 4.1); the opposite lane (x < 0) has none there
    r = Renderer(town, FLAT, cameras=("centre",))
    base = r.ground.base
    t = base.world_to_texel()

    def bright(x, y):
        c, row = (t @ np.array([x, y, 1.0]))[:2]
        return base.albedo[int(round(row)), int(round(c))].astype(int).sum()

    assert bright(1.6, -14.1) > 600 and bright(-1.6, -14.1) < 400
    assert bright(-1.6, 14.1) > 600 and bright(1.6, 14.1) < 400  # northern arm: southbound lane (x < 0)


def _diff_columns(a, b):
    d = np.abs(a.astype(int) - b.astype(int)).sum(-1) > 30
    return np.nonzero(d)


def test_pole_straight_ahead_is_drawn_in_the_centre_column_from_below_the_horizon():
    x, y, yaw = NORTHBOUND
    ahead = 15.0
    pole = Prop("pole", np.array([x, y + MOUNT_FORWARD + ahead]), 8.0, 0.3)
    empty = Renderer(tiny_town(), FLAT, cameras=("centre", "left")).render(*NORTHBOUND)
    with_pole = Renderer(tiny_town(props=[pole]), FLAT, cameras=("centre", "left")).render(*NORTHBOUND)
    ys, xs = _diff_columns(empty["centre"], with_pole["centre"])
    assert len(xs) > 20
    assert abs(xs.mean() - CX) < 1.5 and xs.max() - xs.min() <= 6
    assert ys.max() > HORIZON_ROW + 5 and ys.min() < HORIZON_ROW  # from the ground up into the sky
    # the left camera sees it right of its centre
    ys, xs = _diff_columns(empty["left"], with_pole["left"])
    assert len(xs) > 10 and xs.mean() > CX + 30


def test_building_behind_the_camera_is_not_drawn():
    x, y, yaw = NORTHBOUND
    behind = box(x - 4, y - 12, x + 4, y - 4, h=30.0)  # wholly behind the car, tall
    r0 = Renderer(tiny_town(), FLAT).render(*NORTHBOUND)
    r1 = Renderer(tiny_town(buildings=[behind]), FLAT).render(*NORTHBOUND)
    for cam in CAMERAS:
        assert np.array_equal(r0[cam], r1[cam]), cam


def test_walls_crossing_the_camera_plane_are_clipped():
    x, y, yaw = NORTHBOUND
    beside = box(x + 6, y - 10, x + 14, y + 15, h=20.0)  # alongside on the right, from behind to ahead
    r0 = Renderer(tiny_town(), FLAT).render(*NORTHBOUND)
    r2 = Renderer(tiny_town(buildings=[beside]), FLAT).render(*NORTHBOUND)
    # out of the left camera's view (only the baked contact shadow on the ground nearby changes a little)
    assert len(_diff_columns(r0["left"], r2["left"])[0]) == 0
    ys, xs = _diff_columns(r0["right"], r2["right"])
    assert len(xs) > 2000 and xs.mean() > CX  # a big wall on the right of the right camera
    ys, xs = _diff_columns(r0["centre"], r2["centre"])
    assert len(xs) > 200 and xs.min() > CX  # and at the right edge of the centre camera


def test_buildings_hide_what_is_behind_them():
    x, y, yaw = NORTHBOUND
    wall = box(x - 10, y + 20, x + 10, y + 22, h=20.0, facade=1)  # across the road ahead
    far_pole = Prop("pole", np.array([x, y + 40.0]), 8.0, 0.3)
    a = Renderer(tiny_town(buildings=[wall]), FLAT, cameras=("centre",)).render(*NORTHBOUND)["centre"]
    b = Renderer(tiny_town(buildings=[wall], props=[far_pole]), FLAT, cameras=("centre",)).render(*NORTHBOUND)["centre"]
    assert np.array_equal(a, b)
    near_pole = Prop("pole", np.array([x, y + 12.0]), 8.0, 0.3)
    c = Renderer(tiny_town(buildings=[wall], props=[near_pole]), FLAT, cameras=("centre",)).render(*NORTHBOUND)["centre"]
    ys, xs = _diff_columns(a, c)
    assert len(xs) > 20 and abs(xs.mean() - CX) < 2  # the nearer pole is drawn over the wall


def test_weathers_look_different(town):
    imgs = {w: Renderer(town, w, cameras=("centre",)).render(*NORTHBOUND, t=0.5)["centre"].astype(float)
            for w in ("ClearNoon", "ClearSunset", "MidRainyNoon", "WetCloudySunset")}
    sky = {w: im[:15].reshape(-1, 3).mean(0) for w, im in imgs.items()}
    assert sky["ClearNoon"][2] > sky["ClearNoon"][0] + 30  # blue sky
    assert sky["ClearSunset"][0] > sky["ClearSunset"][2]  # warm sunset sky
    road = {w: im[60:, 60:140].mean() for w, im in imgs.items()}
    assert road["MidRainyNoon"] < road["ClearNoon"]  # wet asphalt is darker
    foggy = Renderer(town, HARSH_WEATHERS["MidRainyNoon"], cameras=("centre",)).render(*NORTHBOUND, t=0.5)
    assert imgs["ClearNoon"].std() > foggy["centre"].astype(float).std()  # fog at 70 m lowers the contrast


def test_items_covering_a_single_pixel_render(town, monkeypatch):
    """Items whose bounding box is one pixel (a far corner in view) composite like any other; OpenCV's
    compare read a 1x1 box as a scalar and raised mid-episode, so the mask is made with numpy."""
    import cv2

    from cicfw.sim.render import renderer as mod

    r = Renderer(town, WEATHERS["ClearNoon"], cameras=("centre",))
    full = r.render(*NORTHBOUND)["centre"]
    real = cv2.boundingRect

    def one_pixel(ids):
        x, y, w, h = real(ids)
        ys, xs = np.nonzero(ids[y:y + h, x:x + w])
        return (x + int(xs[0]), y + int(ys[0]), 1, 1) if len(xs) else (x, y, w, h)

    monkeypatch.setattr(mod.cv2, "boundingRect", one_pixel)
    img = r.render(*NORTHBOUND)["centre"]
    assert img.shape == (88, 200, 3)
    assert np.count_nonzero(np.any(img != full, axis=2)) > 0  # the other item pixels were not drawn ...
    assert np.count_nonzero(np.any(img != full, axis=2)) < 88 * 200  # ... the rest of the frame was
