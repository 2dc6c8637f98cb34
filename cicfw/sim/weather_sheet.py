"""The weather families side by side: ``python -m cicfw.sim.weather_sheet --out docs/img --prefix sim_``.

Writes ``<prefix>weather_families.png``: a row per (town, weather), the centre camera a dozen metres before a
junction under the ``harsh`` preset (left) and the ``carla`` preset derived from CARLA's parameters
(right), labelled with the fog distance, cloud cover, wetness and rain of each.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

from cicfw.core.errors import CicfwError, report_user_errors
from cicfw.core.files import writable_folder, write_together
from cicfw.core.run_folder import claim_folder
from cicfw.sim.preview import (OUT_FOLDER, _first_missing, _png, _remove_empty_folders, approach_pose, check_prefix,
                               load_towns, refuse_twice)
from cicfw.sim.render import Renderer
from cicfw.sim.render.weather import WEATHER_FAMILIES, Weather
from cicfw.sim.town import town_names

FAMILIES = ("harsh", "carla")
PAD, LABEL_W, HEAD = 4, 150, 34


def describe(w: Weather) -> str:
    """One short line of the preset's numbers that the families differ in most."""
    return (f"fog {w.fog_distance:.0f} m, clouds {w.clouds:.2f}, sun {w.sun_elevation:.0f} deg, "
            f"wet {w.wetness:.2f}, rain {w.rain:.2f}")


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.4) -> None:
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)


def sheet(towns: list, weathers: list[str], scale: int = 2, seed: int = 0, t: float = 0.3) -> np.ndarray:
    """The RGB sheet: rows (town, weather), columns the families' centre camera images."""
    h, w = 88 * scale, 200 * scale
    row_h = h + 14 + PAD
    out = np.full((HEAD + len(towns) * len(weathers) * row_h + PAD,
                   LABEL_W + len(FAMILIES) * (w + PAD) + PAD, 3), 255, np.uint8)
    _text(out, "centre camera, 12 m before a junction", (4, 14))
    for k, fam in enumerate(FAMILIES):
        _text(out, f"{fam} family", (LABEL_W + k * (w + PAD) + w // 2 - 40, 30), 0.45)
    r = 0
    for town in towns:
        pose, _ = approach_pose(town, 12.0)
        for name in weathers:
            y = HEAD + r * row_h
            _text(out, town.name, (4, y + h // 2 - 4))
            _text(out, name, (4, y + h // 2 + 14))
            for k, fam in enumerate(FAMILIES):
                wx = WEATHER_FAMILIES[fam][name]
                im = Renderer(town, wx, seed=seed, cameras=("centre",)).render(*pose, t=t)["centre"]
                x = LABEL_W + k * (w + PAD)
                out[y:y + h, x:x + w] = cv2.resize(im, (w, h), interpolation=cv2.INTER_NEAREST)
                _text(out, describe(wx), (x + 2, y + h + 11), 0.32)
            r += 1
    return out


def main(argv: list[str] | None = None) -> int:
    """The command line; every bad value is one line (``cicfw: error: ...``, exit status 2)."""
    return report_user_errors(_main)(argv)


def check_args(a: argparse.Namespace) -> None:
    """One ``CicfwError`` for the first argument outside its domain, before anything is rendered or written."""
    refuse_twice("--weathers", a.weathers)
    for name in a.weathers:
        if any(name not in WEATHER_FAMILIES[fam] for fam in FAMILIES):
            raise CicfwError(f"--weathers: unknown weather {name!r}; known weathers: "
                             f"{', '.join(WEATHER_FAMILIES['carla'])}", key="--weathers", value=name)
    if not (a.colours == 0 or 2 <= a.colours <= 256):
        raise CicfwError(f"--colours must be 0 (full colour) or 2..256, got {a.colours}", key="--colours",
                         value=a.colours)
    check_prefix(a.prefix)


def _main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m cicfw.sim.weather_sheet", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="sim_preview", help="output folder (default: %(default)s)")
    ap.add_argument("--towns", nargs="+", default=town_names())
    ap.add_argument("--weathers", nargs="+", default=list(WEATHER_FAMILIES["carla"]))
    ap.add_argument("--colours", type=int, default=256, help="palette size of the PNG (0: full colour)")
    ap.add_argument("--prefix", default="", help="prefix of the file name (e.g. sim_)")
    a = ap.parse_args(argv)
    check_args(a)
    towns = load_towns(a.towns)  # an unknown town: one line, before the folder is made
    out = Path(a.out).expanduser().resolve()
    new_top = _first_missing(out)
    claim_folder(out, "weather_sheet", "--out", foreign_ok=True)  # not another app's run or dataset
    writable_folder(out, "--out", OUT_FOLDER, "--out")  # before the seconds of rendering
    path = out / f"{a.prefix}weather_families.png"
    try:
        write_together([(path, _png(sheet(towns, a.weathers), a.colours))])
    except BaseException as err:
        _remove_empty_folders(out, new_top)  # a failed run leaves no folder it made
        if isinstance(err, OSError):
            raise CicfwError(f"cannot write {err.filename} ({err.strerror or err}); give a writable --out "
                             f"folder", key="--out", value=str(out)) from None
        raise
    print(path)
    return 0


if __name__ == "__main__":
    from cicfw.core.errors import install_app_handlers

    install_app_handlers()
    sys.exit(main())
