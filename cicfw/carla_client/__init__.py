"""The CARLA 0.9.16 client behind the simulator interface of ``cicfw.sim.backends``.

``backend`` (registry name ``carla``, ``conf/sim/carla.yaml``), ``routes`` (the suite's and the
collector's routes on a CARLA map, planned offline) and ``standin`` (a recording stand-in server for the
tests). It builds on ``cicfw.sim`` and knows no benchmark and no dataset file; the server self-test that
drives the benchmark's runner is the app ``cicfw.carla_client.check``. (Named ``carla_client``, not ``carla``,
so that it can never be taken for the ``carla`` wheel it imports.)
"""
