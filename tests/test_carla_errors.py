"""CARLA's errors are one line each (no server, the client missing, versions differing), found fast with the
real ``carla.Client``; and ``python -m cicfw.carla_client.check`` reports PASS / FAIL per guarantee (here
against the recording stand-in; against a real server it is the user's one-minute self-test)."""
from __future__ import annotations

import io
import socket
import sys
import time
from types import SimpleNamespace

import pytest

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)

carla = pytest.importorskip("carla", reason="the CARLA client is not installed: pip install -e '.[carla]'")

from cicfw.carla_client import check as carla_check  # noqa: E402
from cicfw.carla_client.backend import (CarlaBackend, CarlaError, CarlaNotInstalled,  # noqa: E402
                                        INSTALL_COMMAND, CarlaServerUnavailable, CarlaVersionMismatch, connect,
                                        import_carla)
from carla_standin import StandIn, maps_dir  # noqa: E402
from conftest import assert_refused, run_app_in_process  # noqa: E402

MAPS = maps_dir()
needs_maps = pytest.mark.skipif(MAPS is None, reason="CARLA's Town01/Town02 OpenDRIVE files are not in "
                                                     "../shared/carla-maps (or $CICFW_CARLA_MAPS)")


def unused_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


#: how long the real client waits for a server at an unused port: the failure is the same at any timeout, a short
#: one is less of the suite's time spent waiting
WAIT_S = 0.2


def test_a_real_client_at_an_unused_port_fails_fast_with_one_line():
    port = unused_port()
    t0 = time.monotonic()
    with pytest.raises(CarlaServerUnavailable) as err:
        connect("127.0.0.1", port, connect_timeout_s=WAIT_S)
    assert time.monotonic() - t0 < 4.0
    msg = str(err.value)
    assert "\n" not in msg and f"127.0.0.1:{port}" in msg  # where it looked
    assert "sim.connect_timeout_s" in msg and "sim=embedded" in msg  # the keys that fix it
    assert isinstance(err.value, ValueError)  # the apps print user errors as one line
    # the backend connects lazily, on the first call that needs the server, with the same error
    be = CarlaBackend(host="127.0.0.1", port=port, connect_timeout_s=WAIT_S)
    with pytest.raises(CarlaServerUnavailable) as err:
        be.single_turn_routes("town_a")
    assert f"127.0.0.1:{port}" in str(err.value)


@needs_maps
def test_server_and_client_versions_must_match():
    si = StandIn(MAPS, version="0.9.15")
    fake = SimpleNamespace(Client=lambda host, port: si.client)
    with pytest.raises(CarlaVersionMismatch) as err:
        connect("localhost", 2000, carla=fake)
    msg = str(err.value)
    assert "0.9.15" in msg and "0.9.16" in msg and "\n" not in msg  # both versions
    si.version = "0.9.16"
    assert connect("localhost", 2000, carla=fake) is si.client


def test_a_missing_client_is_one_line_with_the_install_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "carla", None)  # as if it were not installed
    with pytest.raises(CarlaNotInstalled) as err:
        import_carla()
    msg = str(err.value)
    assert INSTALL_COMMAND in msg and "\n" not in msg
    assert isinstance(err.value, ImportError) and isinstance(err.value, ValueError)
    with pytest.raises(CarlaNotInstalled):
        CarlaBackend()


def test_config_errors_name_the_key():
    with pytest.raises(CarlaError) as err:
        CarlaBackend(weathers=["Sunny"], client=object())
    assert "sim.weathers" in str(err.value) and "'Sunny'" in str(err.value)
    with pytest.raises(CarlaError) as err:
        CarlaBackend(sensor_timeout_s=0, client=object())
    assert "sim.sensor_timeout_s" in str(err.value) and "0.0" in str(err.value)
    with pytest.raises(CarlaError) as err:
        CarlaBackend(client=object()).resolve_town("town_z")
    assert "'town_z'" in str(err.value)


@needs_maps
def test_a_map_the_server_lacks_is_one_line_naming_the_town_and_the_maps_it_has():
    si = StandIn(MAPS)
    backend = CarlaBackend(client=si.client, town_map={"town_z": "Town99"})
    for refuse, town in ((lambda: backend.world("town_z"), "town 'town_z': "),
                         (lambda: backend.resolve_town("town_z"), "")):
        with pytest.raises(CarlaError) as err:
            refuse()
        assert str(err.value).startswith(f"{town}map 'Town99' is not on the CARLA server") and "Town01" in str(err.value)


@pytest.mark.parametrize("case", ["evaluate", "collect", "evaluate-no-client"])
def test_the_apps_print_one_line(case, tmp_path, monkeypatch):
    port = unused_port()
    sim = [f"sim.host=127.0.0.1", f"sim.port={port}", f"sim.connect_timeout_s={WAIT_S}"]
    if case == "collect":
        args = ["cicfw.collect", "sim=carla", *sim, f"out_dir={tmp_path / 'data'}"]
    else:
        args = ["cicfw.evaluate", "policy=expert", "sim=carla", *sim, f"hydra.run.dir={tmp_path / 'run'}"]
    if case == "evaluate-no-client":
        monkeypatch.setitem(sys.modules, "carla", None)  # `import carla` raises ImportError, as when not installed
    p = run_app_in_process(*args, cwd=tmp_path)
    assert len([ln for ln in p.stderr.splitlines() if ln.strip()]) == 1, p.stderr[-2000:]
    if case == "evaluate-no-client":
        assert INSTALL_COMMAND in assert_refused(p, "sim=carla")
    else:
        assert_refused(p, "sim.port", f"127.0.0.1:{port}")
    assert not (tmp_path / "data").exists()


@needs_maps
def test_carla_check_passes_on_a_good_server():
    si = StandIn(MAPS, image_size_override=(200, 150))
    out = io.StringIO()
    rep = carla_check.Report(out)
    carla_check.run_checks(client=si.client, report=rep, collect_seconds=3.0)
    text = out.getvalue()
    names = [n for _, n, _ in rep.lines]
    for guarantee in ("error: no server", "server", "map and routes", "expert episode of the suite",
                      "synchronous stepping, one tick per step", "every image is its tick's frame",
                      "steering scaled to the spawned car", "infractions: none while the expert drives",
                      "weather per episode", "infractions: opposite lane, off road, lane invasion sensor",
                      "infractions: collision sensor", "collection episode",
                      "cleanup: no actor left, settings restored"):
        assert guarantee in names, text
    assert rep.failed == 0 and all(s == "PASS" for s, _, _ in rep.lines), text
    assert "72 routes at 12 junctions (24 left / 24 right / 24 straight" in text
    assert si.leftovers() == []


@needs_maps
def test_carla_check_fails_what_breaks_and_still_cleans_up():
    si = StandIn(MAPS, image_size_override=(200, 150))
    si.drop = set(range(si.frame, si.frame + 10_000))  # the cameras never deliver
    out = io.StringIO()
    rep = carla_check.Report(out)
    carla_check.run_checks(client=si.client, report=rep)
    status = {n: s for s, n, _ in rep.lines}
    assert status["map and routes"] == "PASS"
    assert status["expert episode of the suite"] == "FAIL" and "CarlaSensorTimeout" in out.getvalue()
    assert status["cleanup: no actor left, settings restored"] == "PASS"
    assert si.leftovers() == []


def test_carla_check_without_a_server_says_so(capsys):
    rc = carla_check.main(["--host", "127.0.0.1", "--port", str(unused_port()), "--timeout", str(WAIT_S)])
    out = capsys.readouterr().out
    assert rc == 1 and "FAIL  server" in out and "PASS  client" in out


def test_cli_has_carla_check():
    from cicfw.cli import COMMANDS

    assert COMMANDS["carla-check"][0] == "cicfw.carla_client.check"
