"""The embedded driving simulator: towns as data, road graph and router, vehicle, expert, env.

Rendering (cameras, weathers) lives in ``cicfw.sim.render``; the backend interface and the embedded
backend in ``cicfw.sim.backends``. This package imports no benchmark, dataset or CARLA code: the CARLA
client (``cicfw.carla_client``) and the collection stage (``cicfw.collect``) build on it.
"""
