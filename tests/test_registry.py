"""Registry: registration, lookup errors listing names, duplicates, entry-point plugins."""
from __future__ import annotations

import sys
import textwrap
from importlib.metadata import distributions

import pytest

from cicfw.registry import HEADS, MIXERS, Registry, UnknownNameError


def test_register_get_names():
    reg = Registry("widget")

    @reg.register("b")
    class B: ...

    @reg.register("a")
    class A: ...

    assert reg.get("a") is A and reg.get("b") is B
    assert reg.names() == ["a", "b"]
    assert reg.origin("a") == "cicfw"


def test_unknown_name_lists_known():
    with pytest.raises(UnknownNameError) as err:
        MIXERS.get("gtuu")
    assert err.value.value == "gtuu" and "independent" in str(err.value)  # the name, and one registered


def test_duplicate_name_is_refused():
    reg = Registry("widget")
    reg.register("x")(type("X1", (), {}))
    with pytest.raises(ValueError) as err:
        reg.register("x")(type("X2", (), {}))
    assert "'x'" in str(err.value), err.value  # the name taken


def test_builtins_are_registered():
    assert "independent" in MIXERS.names()
    assert "regression" in HEADS.names()


def _install_fake_dist(tmp_path, monkeypatch, name: str, entry_points: str, module_src: str | None = None):
    """A minimal installed distribution (dist-info with entry_points.txt) on sys.path."""
    dist = tmp_path / f"{name}-1.0.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {name}\nVersion: 1.0\n")
    (dist / "entry_points.txt").write_text(textwrap.dedent(entry_points))
    if module_src is not None:
        (tmp_path / f"{name.replace('-', '_')}.py").write_text(textwrap.dedent(module_src))
    monkeypatch.syspath_prepend(str(tmp_path))
    assert any(d.metadata["Name"] == name for d in distributions(path=[str(tmp_path)]))


def test_entry_point_registration(tmp_path, monkeypatch):
    _install_fake_dist(
        tmp_path, monkeypatch, "fake-widgets",
        """
        [cicfw.test_widgets]
        blue = fake_widgets:Blue
        """,
        "class Blue:\n    pass\n",
    )
    reg = Registry("widget", group="cicfw.test_widgets")
    assert reg.names() == ["blue"]
    assert reg.get("blue").__name__ == "Blue"
    assert reg.origin("blue") == "fake-widgets"
    sys.modules.pop("fake_widgets", None)


def test_broken_entry_point_warns_and_is_skipped(tmp_path, monkeypatch):
    _install_fake_dist(
        tmp_path, monkeypatch, "broken-widgets",
        """
        [cicfw.test_broken]
        bad = broken_widgets:Nope
        """,
        "raise ImportError('boom')\n",
    )
    reg = Registry("widget", group="cicfw.test_broken")
    reg.register("good")(type("Good", (), {}))
    with pytest.warns(UserWarning, match="broken-widgets"):
        assert reg.names() == ["good"]
    assert "broken-widgets:bad" in reg.failed
