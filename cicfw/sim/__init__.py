"""The embedded driving simulator: towns as data, road graph and router, vehicle, expert, env.

Rendering (cameras, weathers) lives in ``cicfw.sim.render``; backends (embedded, CARLA) register
in ``cicfw.sim.backends``.
"""
