"""The CIL camera model: intrinsics after CIL's crop and resize, the three mounts, projection.

CIL (Codevilla et al. 2018) records CARLA cameras of 800x600 px with a 100 deg horizontal field of
view, mounted 2.0 m forward of the car's centre and 1.4 m up, pitched down 15 deg; it keeps rows
115:510 and resizes them to 200x88. The numbers below follow that exactly, so the pixel rays of our
images are CIL's (non-square pixels included: fx = 83.9, fy = 74.8; the horizon is at row ~20.7).

Frames: world (x east, y north, z up); vehicle-local (x forward, y left, z up, origin at the pose
point); camera (x right, y down, z forward). Pixel centres are at integer (u, v).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cicfw.core.errors import CicfwError

IMAGE_H, IMAGE_W = 88, 200  # CIL's image after the crop and resize
SRC_W, SRC_H, SRC_FOV_DEG = 800, 600, 100.0  # the CARLA camera CIL cropped from
CROP_TOP, CROP_BOTTOM = 115, 510  # rows of the 800x600 image CIL keeps
PITCH_DEG = 15.0  # downwards
MOUNT_HEIGHT = 1.4  # m above the ground
# CIL mounts the camera 2.0 m forward of the car's centre. The pose the world hands us is the rear
# axle (cicfw.sim.vehicle), whose car centre is length/2 - rear_overhang = 2.25 - 0.9 = 1.35 m ahead.
MOUNT_FORWARD_OF_CENTRE = 2.0
POSE_TO_CAR_CENTRE = 1.35
MOUNT_FORWARD = MOUNT_FORWARD_OF_CENTRE + POSE_TO_CAR_CENTRE  # m ahead of the pose point
NEAR = 0.15  # m, near clipping plane

_F_SRC = (SRC_W / 2) / math.tan(math.radians(SRC_FOV_DEG / 2))  # 335.6 px in the 800x600 image
FX = _F_SRC * IMAGE_W / SRC_W  # 83.9 px
FY = _F_SRC * IMAGE_H / (CROP_BOTTOM - CROP_TOP)  # 74.8 px
CX = (SRC_W / 2) * IMAGE_W / SRC_W - 0.5  # 99.5
CY = (SRC_H / 2 - CROP_TOP) * IMAGE_H / (CROP_BOTTOM - CROP_TOP) - 0.5  # 40.7
K = np.array([[FX, 0.0, CX], [0.0, FY, CY], [0.0, 0.0, 1.0]])
K_INV = np.linalg.inv(K)
HORIZON_ROW = CY - FY * math.tan(math.radians(PITCH_DEG))  # 20.7: rows above see the sky
FIRST_GROUND_ROW = int(math.floor(HORIZON_ROW)) + 1  # first row whose every pixel sees the ground


@dataclass(frozen=True)
class Camera:
    """One of CIL's cameras; ``yaw_deg`` is positive to the right (CIL targets[27])."""

    name: str
    yaw_deg: float
    cam_id: int  # CIL targets[26]

    @property
    def rotation(self) -> np.ndarray:
        """3x3 matrix taking vehicle-local directions to camera directions."""
        return camera_rotation(self.yaw_deg)

    @property
    def position(self) -> np.ndarray:
        """Optical centre in the vehicle-local frame (all three cameras share it)."""
        return np.array([MOUNT_FORWARD, 0.0, MOUNT_HEIGHT])


CAMERAS: dict[str, Camera] = {
    "centre": Camera("centre", 0.0, 0),
    "left": Camera("left", -30.0, 1),
    "right": Camera("right", 30.0, 2),
}


def get_camera(name: str) -> Camera:
    """The camera called ``name``; an unknown name raises a ValueError listing the known ones."""
    if name not in CAMERAS:
        raise CicfwError(f"unknown camera {name!r}; known cameras: {', '.join(CAMERAS)}")
    return CAMERAS[name]


def camera_rotation(yaw_deg: float, pitch_deg: float = PITCH_DEG) -> np.ndarray:
    """Vehicle-local -> camera rotation for a camera yawed ``yaw_deg`` to the right, pitched down."""
    a = -math.radians(yaw_deg)  # local heading angle, CCW
    p = math.radians(pitch_deg)
    h = np.array([math.cos(a), math.sin(a), 0.0])
    right = np.array([math.sin(a), -math.cos(a), 0.0])
    up = np.array([0.0, 0.0, 1.0])
    zc = math.cos(p) * h - math.sin(p) * up
    yc = np.cross(zc, right)  # points down in the image
    return np.stack([right, yc, zc])


def pixel_rays(cam: Camera, rows: slice = slice(None)) -> np.ndarray:
    """(H, W, 3) float32 vehicle-local ray directions of each pixel (camera z component = 1)."""
    v, u = np.mgrid[0:IMAGE_H, 0:IMAGE_W].astype(np.float64)
    d = np.stack([u, v, np.ones_like(u)], -1) @ K_INV.T @ cam.rotation
    return d[rows].astype(np.float32)


def ground_distance_rows() -> np.ndarray:
    """(H,) distance (m, along the ground) from the camera foot to where the centre column of each
    row meets the ground; inf for rows at or above the horizon."""
    v = np.arange(IMAGE_H, dtype=float)
    ang = math.radians(PITCH_DEG) + np.arctan((v - CY) / FY)  # depression angle of the ray
    with np.errstate(divide="ignore"):
        return np.where(ang > 1e-6, MOUNT_HEIGHT / np.tan(np.maximum(ang, 1e-9)), np.inf)
