"""The weather families: CARLA's committed parameters, the rule that derives our presets from them
(recomputed here from the published formulas), the harsh family kept as it was, and the switches that
pick a family (the embedded backend, a dataset's hash, a reproduction's pin)."""
from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import pytest

from cicfw.sim.render.carla_weather import ANCHORS, CARLA_PRESETS, derive
from cicfw.sim.render.weather import (CARLA_WEATHERS, DEFAULT_FAMILY, HARSH_WEATHERS, LEGACY_FAMILY, WEATHERS,
                                      get_weather, weather_family)

REPO = Path(__file__).resolve().parents[1]
DERIVED = [n for n in CARLA_WEATHERS if n not in ANCHORS]


# ------------------------------------------------------------------------------------------------
# CARLA's own values


def test_the_committed_table_is_carlas_own():
    carla = pytest.importorskip("carla", reason="the carla client library is not installed (pip install cicfw[carla])")
    for name, fields in CARLA_PRESETS.items():
        preset = getattr(carla.WeatherParameters, name)
        library = {f for f in dir(preset) if not f.startswith("_") and isinstance(getattr(preset, f), float)}
        assert set(fields) == library, name  # every field, none made up
        for field, value in fields.items():
            assert getattr(preset, field) == value, f"{name}.{field}"


def test_every_embedded_weather_is_a_carla_preset_the_carla_backend_can_set():
    from cicfw.carla_client.backend import DEFAULT_WEATHERS

    assert set(DEFAULT_WEATHERS) <= set(CARLA_PRESETS) == set(WEATHERS)


# ------------------------------------------------------------------------------------------------
# the rule, recomputed


def luma(c):
    return 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]


def kasten_czeplak(n):
    """(global, beam) horizontal light under cloud cover n, relative to a clear sky (KC 1980)."""
    g = 1 - 0.75 * n ** 3.4
    return g, g * (1 - (0.3 + 0.7 * n * n))


ANCHOR = {"ClearNoon": "ClearNoon", "CloudyNoon": "ClearNoon", "MidRainyNoon": "ClearNoon",
          "HardRainNoon": "ClearNoon", "WetCloudySunset": "ClearSunset"}


@pytest.mark.parametrize("name", DERIVED)
def test_derived_presets_follow_the_rule(name):
    carla, base = CARLA_PRESETS[name], CARLA_PRESETS[ANCHOR[name]]
    a, w = HARSH_WEATHERS[ANCHOR[name]], CARLA_WEATHERS[name]
    n, n0 = carla["cloudiness"] / 100, base["cloudiness"] / 100
    assert w.sun_elevation == a.sun_elevation + carla["sun_altitude_angle"] - base["sun_altitude_angle"]
    assert w.clouds == pytest.approx(a.clouds + (n - n0) * (1 - a.clouds) / (1 - n0))
    (g, b), (g0, b0) = kasten_czeplak(n), kasten_czeplak(n0)
    assert w.sun == pytest.approx(tuple(c * b / b0 for c in a.sun))
    # the horizontal light (ambient + sun on the ground) follows KC's global ratio
    el = math.sin(math.radians(a.sun_elevation))
    assert luma(w.ambient) + luma(w.sun) * el == pytest.approx((luma(a.ambient) + luma(a.sun) * el) * g / g0)
    # fog: UE4's base-2 line integral of FogDensity (= fog_density / 100) / 1000 per cm
    extinction = math.log(2) * math.log(2) * carla["fog_density"] / 100 / 1000 * 100  # per metre
    extinction0 = math.log(2) * math.log(2) * base["fog_density"] / 100 / 1000 * 100
    assert 1 / w.fog_distance == pytest.approx(1 / a.fog_distance + extinction - extinction0)
    assert w.rain == carla["precipitation"] / 100 and w.puddles == carla["precipitation_deposits"] / 100
    assert w.wetness == max(carla["precipitation_deposits"], carla["wetness"]) / 100


def test_a_few_derived_values_by_hand():
    mid, wet, hard = (CARLA_WEATHERS[n] for n in ("MidRainyNoon", "WetCloudySunset", "HardRainNoon"))
    assert mid.fog_distance == pytest.approx(523.83, abs=0.01)  # 1 / (1/700 + 0.480453/1000)
    assert hard.fog_distance == pytest.approx(261.04, abs=0.01)  # 1 / (1/700 + 5 x 0.480453/1000)
    assert wet.fog_distance == 380.0  # CARLA's fog density equals ClearSunset's
    assert mid.sun[0] == pytest.approx(0.62 * 0.38883 / 0.69823, abs=1e-4)  # KC beam at 60 % vs 5 % cover
    assert hard.sun == (0.0, 0.0, 0.0)  # no direct sun under full cover
    assert (mid.sun_elevation, wet.sun_elevation) == (62, 7)  # CARLA keeps its clear presets' sun
    assert (mid.wetness, mid.puddles, mid.rain) == (0.6, 0.6, 0.6)
    assert (wet.wetness, wet.puddles, wet.rain) == (0.5, 0.5, 0.0)


@pytest.mark.parametrize("name", ANCHORS)
def test_the_anchors_are_the_rules_fixed_points(name):
    a = HARSH_WEATHERS[name]
    again = derive(name, a, CARLA_PRESETS[name], CARLA_PRESETS[name])
    for field in ("sun", "ambient", "sky_zenith", "sky_horizon", "cloud_lit", "cloud_dark"):
        assert getattr(again, field) == pytest.approx(getattr(a, field), abs=1e-12), field
    for field in ("clouds", "fog_distance", "sun_elevation", "sun_glow", "wetness", "puddles", "rain"):
        assert getattr(again, field) == pytest.approx(getattr(a, field), abs=1e-12), field


def test_a_field_the_renderer_cannot_show_must_not_differ():
    other = {**CARLA_PRESETS["MidRainyNoon"], "dust_storm": 50.0}
    with pytest.raises(ValueError) as err:
        derive("MidRainyNoon", HARSH_WEATHERS["ClearNoon"], other, CARLA_PRESETS["ClearNoon"])
    assert all(s in str(err.value) for s in ("dust_storm", "50.0", "0.0")), err.value  # the field, both values


# ------------------------------------------------------------------------------------------------
# the families


def test_the_harsh_family_is_the_hand_set_presets_unchanged():
    mid, wet = HARSH_WEATHERS["MidRainyNoon"], HARSH_WEATHERS["WetCloudySunset"]
    assert (mid.fog_distance, mid.clouds, mid.sun, mid.wetness, mid.rain) == (70.0, 1.0, (0.0, 0.0, 0.0), 0.9, 0.45)
    assert (wet.fog_distance, wet.sun_elevation, wet.clouds, wet.wetness, wet.puddles) == (160.0, 7, 0.75, 1.0, 0.8)
    for name in ANCHORS:  # the training presets are one object in both families: the default dataset is unchanged
        assert CARLA_WEATHERS[name] is HARSH_WEATHERS[name]
    assert (DEFAULT_FAMILY, LEGACY_FAMILY) == ("carla", "harsh") and WEATHERS is CARLA_WEATHERS


def test_a_family_is_picked_by_name_and_an_unknown_one_lists_the_known():
    assert get_weather("MidRainyNoon", "harsh") is HARSH_WEATHERS["MidRainyNoon"]
    assert get_weather("MidRainyNoon") is CARLA_WEATHERS["MidRainyNoon"]
    with pytest.raises(ValueError) as err:
        weather_family("soft")
    assert (err.value.key, err.value.value) == ("weather_family", "soft")
    assert "carla" in str(err.value) and "harsh" in str(err.value)  # the known ones


def test_the_embedded_backend_renders_a_name_in_its_family(tmp_path):
    from omegaconf import OmegaConf

    from cicfw.sim.backends import EmbeddedBackend

    assert OmegaConf.load(REPO / "conf" / "sim" / "embedded.yaml").weather_family == DEFAULT_FAMILY
    assert EmbeddedBackend().weather_family == DEFAULT_FAMILY
    for family, presets in (("carla", CARLA_WEATHERS), ("harsh", HARSH_WEATHERS)):
        backend = EmbeddedBackend(weather_family=family)
        route = backend.single_turn_routes("town_a")[0]
        env = backend.make_env("town_a", route, "MidRainyNoon", renderer=False)
        assert env.weather is presets["MidRainyNoon"]
    with pytest.raises(ValueError) as err:
        EmbeddedBackend(weather_family="wet")
    assert (err.value.key, err.value.value) == ("sim.weather_family", "wet")


def test_a_dataset_hash_names_the_family_only_where_it_changes_the_data():
    from cicfw.collect.config import _NOT_DATA, config_hash, resolve_config

    def pre_family_hash(cfg):  # the hash as computed before the families (embedded simulator)
        keep = {k: v for k, v in cfg.items() if k not in _NOT_DATA}
        return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:16]

    harsh = {"name": "embedded", "weather_family": "harsh"}
    default = resolve_config({})
    assert config_hash(default) == pre_family_hash(default) == "508d1f9ec723c91a"  # docs/results/*'s dataset
    assert config_hash(resolve_config({"sim": harsh})) == config_hash(default)  # training weathers: one rendering
    rainy_harsh = resolve_config({"weathers": ["MidRainyNoon"], "sim": harsh})
    rainy = resolve_config({"weathers": ["MidRainyNoon"]})
    assert config_hash(rainy_harsh) == pre_family_hash(rainy_harsh)  # data collected before keeps its hash
    assert config_hash(rainy) != config_hash(rainy_harsh)


# ------------------------------------------------------------------------------------------------
# a reproduction's pin


def test_overrides_name_a_family_explicitly():
    from cicfw.benchmark.suite import named_weather_family, with_weather_family

    assert with_weather_family(["suite=single_turn"]) == ["suite=single_turn", "sim.weather_family=carla"]
    assert with_weather_family(["suite=single_turn"], default="harsh")[-1] == "sim.weather_family=harsh"
    assert with_weather_family(["sim.weather_family=harsh"]) == ["sim.weather_family=harsh"]
    assert with_weather_family(["sim.weather_family=harsh"], "carla")[-1] == "sim.weather_family=carla"
    assert with_weather_family(["sim=carla", "suite.limit=1"]) == ["sim=carla", "suite.limit=1"]  # CARLA's own
    assert named_weather_family(["a=1", "++sim.weather_family=harsh"]) == "harsh"
    assert named_weather_family(["suite=single_turn"]) is None


def test_continuing_a_folder_pinned_before_the_families_keeps_its_harsh_weathers():
    from cicfw.reproduction import app as reproduce

    published = json.loads((REPO / "docs" / "results" / "converged6" / "reproduce.json").read_text())["pinned"]
    assert "sim.weather_family" not in " ".join(published["suite"])  # pinned before the families
    cfg = reproduce.compose_plan(["budget=converged6"])
    with pytest.raises(reproduce.ReproduceError) as err:
        reproduce.refuse_other_pin("continue_from", "fix", published, reproduce.fingerprint(cfg, None), cfg,
                                   ("budget", "train", "suite"))
    assert "weather_family=harsh" in str(err.value)  # the override that continues it
    cfg = reproduce.compose_plan(["budget=converged6", "weather_family=harsh"])
    ours = reproduce.fingerprint(cfg, None)
    assert ours["suite"][-1] == "sim.weather_family=harsh"
    assert reproduce.pinned_differences(published, ours, cfg, ("budget", "train", "suite")) == []


def test_the_sheet_shows_the_families_side_by_side():
    import numpy as np

    from cicfw.sim.town import load_town
    from cicfw.sim.weather_sheet import HEAD, LABEL_W, PAD, sheet

    img = sheet([load_town("town_b")], ["ClearNoon", "MidRainyNoon"], scale=1)
    row_h, w = 88 + 14 + PAD, 200

    def camera(row, column):
        y, x = HEAD + row * row_h, LABEL_W + column * (w + PAD)
        return img[y:y + 88, x:x + w].astype(int)

    assert np.array_equal(camera(0, 0), camera(0, 1))  # a training weather: one preset in both families
    assert np.abs(camera(1, 0) - camera(1, 1)).mean() > 5  # MidRainyNoon: harsh fog at 70 m vs 524 m
