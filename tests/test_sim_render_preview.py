"""python -m cicfw.sim.preview: the sheets and the map are written (one town, one weather: fast)."""
import cv2
import pytest

from cicfw.core.errors import CicfwError
from cicfw.sim import preview

pytestmark = pytest.mark.slow  # trains, collects, drives or runs an app (pytest -m "not slow" skips it)


def test_preview_writes_sheets_and_maps(tmp_path, capsys):
    out = tmp_path / "pics"
    assert preview.main(["--out", str(out), "--towns", "town_b", "--weathers", "ClearNoon", "--scale", "1",
                         "--routes", "2", "--colours", "64", "--prefix", "x_"]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == ["x_contact_sheet.png", "x_map_town_b.png", "x_turn_sheet.png"]  # nothing half-written
    sheet = cv2.imread(str(out / "x_contact_sheet.png"))
    assert sheet.shape[0] >= 88 and sheet.shape[1] >= 3 * 200  # one row of three camera images
    town_map = cv2.imread(str(out / "x_map_town_b.png"))
    assert min(town_map.shape[:2]) > 300
    assert str(out / "x_map_town_b.png") in capsys.readouterr().out


def test_preview_rejects_unknown_weather(tmp_path, capsys):
    with pytest.raises(SystemExit):
        preview.main(["--out", str(tmp_path), "--weathers", "Foggy"])
    err = capsys.readouterr().err
    assert "unknown weather 'Foggy'" in err and "ClearNoon" in err


def test_preview_draws_the_weather_family_it_is_given(tmp_path):
    """The two families render MidRainyNoon differently (harsh: overcast, fog at 70 m)."""
    sheets = {}
    for family in ("carla", "harsh"):
        out = tmp_path / family
        assert preview.main(["--out", str(out), "--towns", "town_b", "--weathers", "MidRainyNoon", "--scale", "1",
                             "--routes", "0", "--weather-family", family]) == 0
        sheets[family] = cv2.imread(str(out / "contact_sheet.png"))
    assert sheets["carla"].shape == sheets["harsh"].shape
    assert (sheets["carla"] != sheets["harsh"]).mean() > 0.1  # the pictures, not only the title


def test_preview_rejects_an_unknown_weather_family_before_writing(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        preview.main(["--out", str(tmp_path / "pics"), "--weather-family", "gloomy"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'gloomy'" in err[0] and "carla" in err[0] and "harsh" in err[0], err
    assert not (tmp_path / "pics").exists()
    with pytest.raises(CicfwError) as refused:  # this command's option, not a run's sim.weather_family
        preview.check_weathers(["ClearNoon"], "gloomy")
    assert (refused.value.key, refused.value.value) == ("--weather-family", "gloomy")


@pytest.mark.parametrize("args, option, twice", [
    (["--towns", "town_b", "town_b", "--weathers", "ClearNoon"], "--towns", "town_b"),
    (["--towns", "town_b", "--weathers", "ClearNoon", "CloudyNoon", "ClearNoon"], "--weathers", "ClearNoon"),
])
def test_preview_refuses_a_town_or_weather_listed_twice_before_writing(tmp_path, args, option, twice):
    with pytest.raises(CicfwError) as err:
        preview._main(["--out", str(tmp_path / "pics"), *args])
    assert (err.value.key, err.value.value) == (option, twice)
    assert not (tmp_path / "pics").exists()


def _preview(out, *extra: str) -> int:
    return preview.main(["--out", str(out), "--towns", "town_b", "--weathers", "ClearNoon", "--scale", "1",
                         "--routes", "0", *extra])


def test_a_user_s_file_of_a_picture_s_name_is_kept_unless_overwrite(tmp_path, capsys):
    from PIL import Image

    out = tmp_path / "pics"
    out.mkdir()
    (out / "turn_sheet.png").write_bytes(b"my own turn sheet")
    with pytest.raises(SystemExit) as exit_:
        _preview(out)
    line = capsys.readouterr().err.strip()
    assert exit_.value.code == 2 and line.startswith("cicfw: error:") and "--out" in line and "turn_sheet.png" in line
    assert sorted(p.name for p in out.iterdir()) == ["turn_sheet.png"]
    assert (out / "turn_sheet.png").read_bytes() == b"my own turn sheet"
    assert _preview(out, "--overwrite") == 0
    for name in ("contact_sheet.png", "turn_sheet.png", "map_town_b.png"):
        with Image.open(out / name) as img:  # PIL reads the mark (and checks its CRC) as a valid PNG's text
            assert img.info["Software"] == "cicfw preview", name
            img.load()
    assert _preview(out) == 0  # a preview's own pictures are replaced without the option
