"""The CIL camera model: intrinsics, mounts, projection (no town needed)."""
import math

import numpy as np
import pytest

from cicfw.sim.render import camera as cm
from cicfw.sim.render.camera import (CAMERAS, CX, CY, FX, FY, HORIZON_ROW, IMAGE_H, IMAGE_W, NEAR, Camera,
                                     get_camera)


def local_to_camera(points: np.ndarray, cam: Camera) -> np.ndarray:
    """(..., 3) vehicle-local points -> camera coordinates."""
    return (np.asarray(points, float) - cam.position) @ cam.rotation.T


def world_to_local(points: np.ndarray, x: float, y: float, yaw: float) -> np.ndarray:
    """(..., 2 or 3) world points -> vehicle-local (pose (x, y, yaw) of the vehicle)."""
    p = np.array(points, float)
    c, s = math.cos(yaw), math.sin(yaw)
    dx, dy = p[..., 0] - x, p[..., 1] - y
    p[..., 0], p[..., 1] = c * dx + s * dy, -s * dx + c * dy
    return p


def project_world(points: np.ndarray, pose: tuple[float, float, float], cam: Camera
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(N, 3) world points -> (u, v, visible); a point behind the near plane is not visible."""
    pc = local_to_camera(world_to_local(points, *pose), cam)
    z = pc[..., 2]
    zs = np.where(z > NEAR, z, np.nan)
    u, v = FX * pc[..., 0] / zs + CX, FY * pc[..., 1] / zs + CY
    vis = (z > NEAR) & (u >= -0.5) & (u < IMAGE_W - 0.5) & (v >= -0.5) & (v < IMAGE_H - 0.5)
    return u, v, vis


def test_intrinsics_follow_cils_crop():
    # 800x600, 100 deg FOV, rows 115:510 resized to 200x88
    f = 400 / math.tan(math.radians(50))
    assert FX == pytest.approx(f / 4)
    assert FY == pytest.approx(f * 88 / 395)
    assert CX == pytest.approx(99.5)
    assert CY == pytest.approx((300 - 115) * 88 / 395 - 0.5)
    assert HORIZON_ROW == pytest.approx(20.68, abs=0.01)
    assert cm.FIRST_GROUND_ROW == 21


def test_mount_is_cils_relative_to_the_world_pose():
    from cicfw.sim.vehicle import VehicleParams

    p = VehicleParams()
    # CIL: 2.0 m ahead of the car's centre; the world's pose is the rear axle
    assert cm.MOUNT_FORWARD == pytest.approx(2.0 + p.length / 2 - p.rear_overhang)
    assert cm.MOUNT_HEIGHT == 1.4 and cm.PITCH_DEG == 15.0
    assert [c.yaw_deg for c in CAMERAS.values()] == [0.0, -30.0, 30.0]
    assert [c.cam_id for c in CAMERAS.values()] == [0, 1, 2]


@pytest.mark.parametrize("yaw", [0.0, 1.0, -2.5])
def test_lane_point_straight_ahead_lands_in_centre_column_below_horizon(yaw):
    x, y = 10.0, -4.0
    c, s = math.cos(yaw), math.sin(yaw)
    for dist in (5.0, 20.0, 60.0):
        d = cm.MOUNT_FORWARD + dist
        u, v, vis = project_world(np.array([[x + d * c, y + d * s, 0.0]]), (x, y, yaw), CAMERAS["centre"])
        assert vis[0]
        assert u[0] == pytest.approx(CX, abs=1e-6)  # the centre column (between pixels 99 and 100)
        assert v[0] > HORIZON_ROW
    # nearer points are lower in the image
    us, vs, _ = project_world(np.array([[x + (cm.MOUNT_FORWARD + d) * c, y + (cm.MOUNT_FORWARD + d) * s, 0.0]
                                        for d in (5.0, 20.0)]), (x, y, yaw), CAMERAS["centre"])
    assert vs[0] > vs[1]


def test_point_behind_the_camera_is_not_visible():
    pose = (0.0, 0.0, 0.0)
    for cam in CAMERAS.values():
        for p in ([-5.0, 0.0, 0.0], [-5.0, 0.0, 3.0], [cm.MOUNT_FORWARD - 0.05, 0.0, 1.4]):
            _, _, vis = project_world(np.array([p]), pose, cam)
            assert not vis[0], (cam.name, p)


def test_side_cameras_see_the_road_ahead_off_centre():
    pose, ahead = (0.0, 0.0, math.pi / 2), np.array([[0.0, 25.0, 0.0]])  # facing north
    ul, _, vl = project_world(ahead, pose, CAMERAS["left"])
    ur, _, vr = project_world(ahead, pose, CAMERAS["right"])
    assert vl[0] and vr[0]
    assert ul[0] > CX + 30  # the left camera looks left: straight ahead is right of its centre
    assert ur[0] < CX - 30
    # a ground point 30 deg left of the car's heading (seen from the camera) is on the left camera's axis
    dy = 25.0 - cm.MOUNT_FORWARD
    ul2, _, vis = project_world(np.array([[-dy * math.tan(math.radians(30)), 25.0, 0.0]]), pose, CAMERAS["left"])
    assert vis[0] and abs(ul2[0] - CX) < 3


def test_left_is_left():
    """A point to the car's left (world frame) projects to the left half of the centre image."""
    pose = (0.0, 0.0, 0.0)  # facing east: north (+y) is the car's left
    u, _, vis = project_world(np.array([[20.0, 3.0, 0.0], [20.0, -3.0, 0.0]]), pose, CAMERAS["centre"])
    assert vis.all() and u[0] < CX < u[1]


def ground_to_image(cam, x: float, y: float, yaw: float) -> np.ndarray:
    """3x3 homography taking world ground points (x, y, 1) to image (u, v, 1)."""
    c, s = math.cos(yaw), math.sin(yaw)
    # world ground (X, Y, 1) -> local 3D point minus the camera position
    m = np.array([[c, s, -(c * x + s * y) - cm.MOUNT_FORWARD],
                  [-s, c, (s * x - c * y)],
                  [0.0, 0.0, -cm.MOUNT_HEIGHT]])
    return cm.K @ cam.rotation @ m


def test_pixel_rays_and_ground_homography_agree():
    cam = get_camera("right")
    pose = (3.0, 7.0, 0.4)
    rays = cm.pixel_rays(cam)
    hom = ground_to_image(cam, *pose)
    for (v, u) in [(40, 20), (80, 150), (30, 100)]:
        d = rays[v, u].astype(float)
        t = -cm.MOUNT_HEIGHT / d[2]
        local = np.array([cm.MOUNT_FORWARD, 0.0]) + t * d[:2]
        c, s = math.cos(pose[2]), math.sin(pose[2])
        world = np.array([pose[0] + c * local[0] - s * local[1], pose[1] + s * local[0] + c * local[1], 1.0])
        img = hom @ world
        assert img[0] / img[2] == pytest.approx(u, abs=1e-3)
        assert img[1] / img[2] == pytest.approx(v, abs=1e-3)


def test_unknown_camera_lists_the_known_ones():
    with pytest.raises(ValueError, match="centre, left, right"):
        get_camera("rear")
