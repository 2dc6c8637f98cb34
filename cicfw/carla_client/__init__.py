"""The CARLA 0.9.16 client behind the simulator interface of ``cicfw.sim.backends``.

``backend`` (registry name ``carla``, ``conf/sim/carla.yaml``) and ``routes`` (the suite's and the
collector's routes on a CARLA map, planned offline). It builds on ``cicfw.sim`` and knows no benchmark
and no dataset file; the server self-test that drives the benchmark's runner is the app
``cicfw.carla_client.check``; the tests' recording stand-in server is ``tests/carla_standin.py``. (Named ``carla_client``, not ``carla``,
so that it can never be taken for the ``carla`` wheel it imports.)
"""
