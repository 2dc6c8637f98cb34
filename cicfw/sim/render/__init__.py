"""Camera images for the embedded simulator: CIL's three cameras over a town, under named weathers.

``Renderer(town, weather, seed=0, cameras=("centre", "left", "right")).render(x, y, yaw, t)`` returns
``{camera: (88, 200, 3) uint8 RGB}``. See camera.py (the CIL camera model), weather.py (presets),
ground.py (baked ground textures), scene.py (walls and props), renderer.py (the per-frame pipeline).
"""
from cicfw.sim.render.camera import CAMERAS, IMAGE_H, IMAGE_W, Camera, get_camera
from cicfw.sim.render.renderer import Renderer, clear_caches
from cicfw.sim.render.weather import NEW_WEATHERS, TRAINING_WEATHERS, WEATHERS, Weather, get_weather

__all__ = ["CAMERAS", "IMAGE_H", "IMAGE_W", "Camera", "get_camera", "Renderer", "clear_caches", "NEW_WEATHERS",
           "TRAINING_WEATHERS", "WEATHERS", "Weather", "get_weather"]
