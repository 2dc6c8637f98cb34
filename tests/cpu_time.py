"""Opt-in pytest plugin: the CPU seconds each test costs, printed at the end
(`PYTHONPATH=. pytest -p tests.cpu_time`, from the repository root).

CPU time, not wall time, because the suite's machine is shared: a loaded machine stretches wall seconds but
not the CPU a test spends. A test's figure is this process's CPU (``time.process_time()``) plus that of the
child processes it started and reaped (``getrusage(RUSAGE_CHILDREN)``), over its setup, call and teardown
(a shared fixture is charged to the first test that sets it up). Works under pytest-xdist: each worker
measures its tests and the figures travel to the controller in the reports' ``user_properties``."""
from __future__ import annotations

import os
import resource
import time
from collections import defaultdict

import pytest

_KEY = "cpu_time_s"
TOP = 30


def _cpu_now() -> float:
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


_PHASES = pytest.StashKey[dict]()


def _charge(item, when: str):
    """Run one phase of a test (a hook wrapper's body) and keep the CPU it spent."""
    start = _cpu_now()
    try:
        return (yield)
    finally:
        item.stash.setdefault(_PHASES, {})[when] = _cpu_now() - start


@pytest.hookimpl(wrapper=True)
def pytest_runtest_setup(item):
    return (yield from _charge(item, "setup"))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item):
    return (yield from _charge(item, "call"))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_teardown(item, nextitem):
    return (yield from _charge(item, "teardown"))


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    report = yield
    spent = item.stash.get(_PHASES, {}).get(call.when)
    if spent is not None:
        report.user_properties.append((_KEY, spent))
    return report


class _Totals:
    """Collects the figures from every report (the controller's, under xdist) and prints them."""

    def __init__(self) -> None:
        self.per_test: dict[str, float] = defaultdict(float)

    @pytest.hookimpl
    def pytest_runtest_logreport(self, report):
        for key, value in report.user_properties:
            if key == _KEY:
                self.per_test[report.nodeid] += value

    @pytest.hookimpl
    def pytest_terminal_summary(self, terminalreporter):
        if not self.per_test:
            return
        write = terminalreporter.write_line
        per_file: dict[str, float] = defaultdict(float)
        for nodeid, seconds in self.per_test.items():
            per_file[nodeid.split("::", 1)[0]] += seconds
        terminalreporter.section(f"CPU seconds (process + children), top {TOP} tests")
        for nodeid, seconds in sorted(self.per_test.items(), key=lambda kv: -kv[1])[:TOP]:
            write(f"{seconds:8.2f}  {nodeid}")
        terminalreporter.section(f"CPU seconds per file, top {TOP}")
        for path, seconds in sorted(per_file.items(), key=lambda kv: -kv[1])[:TOP]:
            write(f"{seconds:8.2f}  {path}")
        write(f"{sum(self.per_test.values()):8.2f}  total over {len(self.per_test)} tests "
              f"(pid {os.getpid()} prints; collection and start-up are not counted)")


def pytest_configure(config):
    if not hasattr(config, "workerinput"):  # the controller (or a run without xdist) prints
        config.pluginmanager.register(_Totals(), "cpu_time_totals")
