"""Pictures of the embedded simulator: ``python -m cicfw.sim.preview --out DIR``.

Writes ``contact_sheet.png`` (the three cameras x the weathers x the towns, a dozen metres before a
junction), ``turn_sheet.png`` (the cameras in the middle of a left turn), both in the ``--weather-family`` a
run names as ``sim.weather_family``, and ``map_<town>.png`` (a top-down map drawn from the renderer's ground
texture with buildings, trees and a few routes coloured by their high-level command). A bad value (unknown
town or weather, a missing or broken town file, an unwritable folder) prints one line, ``cicfw: error:
...``, and exits with status 2.
"""
from __future__ import annotations

import argparse
import io
import math
import os
import struct
import sys
import zlib
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from cicfw.core.errors import CicfwError, ConfigError, report_user_errors
from cicfw.core.files import writable_folder, write_together
from cicfw.core.run_folder import claim_folder
from cicfw.sim.backends import EmbeddedBackend
from cicfw.sim.render import CAMERAS, WEATHERS, Renderer
from cicfw.sim.render.camera import MOUNT_FORWARD
from cicfw.sim.render.weather import DEFAULT_FAMILY, WEATHER_FAMILIES, get_weather
from cicfw.sim.roadgraph import road_graph, single_turn_routes
from cicfw.sim.town import load_town, town_names

CAMERA_ORDER = ("left", "centre", "right")
# CIL command code -> (label, RGB)
COMMAND_STYLE = {2: ("follow", (255, 255, 255)), 3: ("left", (40, 120, 230)), 4: ("right", (230, 50, 50)),
                 5: ("straight", (40, 190, 70))}


def _png(rgb: np.ndarray, colours: int = 0) -> bytes:
    """The PNG file of ``rgb``; ``colours`` > 0 quantises to a palette (small files for docs)."""
    if colours:
        buf = io.BytesIO()
        Image.fromarray(rgb).quantize(colours, method=Image.Quantize.FASTOCTREE,
                                      dither=Image.Dither.NONE).save(buf, format="PNG", optimize=True)
        return buf.getvalue()
    ok, data = cv2.imencode(".png", np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise ValueError("the image could not be encoded as PNG")
    return data.tobytes()


#: the tEXt chunk's content every preview PNG carries: a file that holds it is preview's own, which the next
#: preview into the folder replaces; any other file of a picture's name is the user's, kept
PNG_MARK = b"Software\x00cicfw preview"
_PNG_HEAD = 33  # the 8-byte signature and the IHDR chunk (13 bytes of data), which every PNG opens with


def marked_png(png: bytes) -> bytes:
    """``png`` with preview's tEXt chunk right after its header."""
    chunk = b"tEXt" + PNG_MARK
    return png[:_PNG_HEAD] + struct.pack(">I", len(PNG_MARK)) + chunk + struct.pack(">I", zlib.crc32(chunk)) \
        + png[_PNG_HEAD:]


def is_preview_png(path: Path) -> bool:
    """Whether ``path`` is a PNG a preview wrote (its mark right after the header)."""
    want = struct.pack(">I", len(PNG_MARK)) + b"tEXt" + PNG_MARK
    try:
        with open(path, "rb") as f:
            return f.read(_PNG_HEAD + len(want))[_PNG_HEAD:] == want
    except OSError:  # a folder of that name, an unreadable file: not a picture preview may replace
        return False


def picture_names(prefix: str, towns: list) -> list[str]:
    """The file names a preview writes: the two sheets and a map per town."""
    return [f"{prefix}contact_sheet.png", f"{prefix}turn_sheet.png", *(f"{prefix}map_{t.name}.png" for t in towns)]


def check_overwrites(out: Path, names: list[str], overwrite: bool) -> None:
    """A file of a picture's name in ``out`` that no preview wrote (the user's own ``contact_sheet.png``) is
    refused in one line before anything is rendered, unless ``--overwrite``."""
    theirs = [n for n in names if os.path.lexists(out / n) and not is_preview_png(out / n)]
    if theirs and not overwrite:
        raise CicfwError(f"--out {str(out)!r} already holds {', '.join(theirs)}, which no preview wrote; give another "
                         f"--out, or --overwrite to replace them", key="--out", value=str(out))


#: what ``--out`` must be (``writable_folder`` checks it before anything is rendered)
OUT_FOLDER = "a folder you can write (created if missing) for the PNGs"


def _label(img: np.ndarray, text: str, org: tuple[int, int], scale: float = 0.42, colour=(0, 0, 0)) -> None:
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)


def pose_on_route(route, s: float) -> tuple[float, float, float]:
    """Vehicle pose (rear axle) at arc length ``s`` of a route."""
    i = int(np.clip(np.searchsorted(route.s, s), 0, len(route.s) - 1))
    return float(route.points[i, 0]), float(route.points[i, 1]), float(route.heading[i])


def approach_pose(town, before: float = 12.0, command: int = 3):
    """A pose whose cameras are ``before`` metres ahead of a junction's entry, on a route that turns
    ``command`` there (an X junction if the town has one), and that route."""
    routes = single_turn_routes(town)
    arms = {j.id: len(j.arms) for j in town.junctions}
    routes.sort(key=lambda r: (-arms[r.meta["junction"]], r.meta["command"] != command, r.name))
    for r in routes:
        s_entry = r.turns[0][2]
        s = s_entry - before - MOUNT_FORWARD
        if s >= 0:
            return pose_on_route(r, s), r
    r = routes[0]
    return pose_on_route(r, 0.0), r


def _grid(rows: list[tuple[str, dict]], scale: int, title: str) -> np.ndarray:
    """Rows of (label, {camera: image}) -> one labelled sheet (RGB)."""
    pad, lab_w = 3, 130
    h, w = 88 * scale, 200 * scale
    head = 40
    out = np.full((head + len(rows) * (h + pad) + pad, lab_w + 3 * (w + pad) + pad, 3), 255, np.uint8)
    _label(out, title, (4, 15), 0.42)
    for k, cam in enumerate(CAMERA_ORDER):
        _label(out, f"{cam} ({CAMERAS[cam].yaw_deg:+.0f} deg)", (lab_w + k * (w + pad) + w // 2 - 45, 34), 0.42)
    for r, (label, ims) in enumerate(rows):
        y = head + r * (h + pad) + pad
        for i, line in enumerate(label.split("\n")):
            _label(out, line, (4, y + h // 2 - 6 + 16 * i), 0.42)
        for k, cam in enumerate(CAMERA_ORDER):
            im = ims[cam]
            if scale != 1:
                im = cv2.resize(im, (w, h), interpolation=cv2.INTER_NEAREST)
            x = lab_w + k * (w + pad) + pad
            out[y:y + h, x:x + w] = im
    return out


def contact_sheet(towns: list, weathers: list[str], scale: int = 1, seed: int = 0, t: float = 0.3,
                  before: float = 12.0, family: str = DEFAULT_FAMILY) -> np.ndarray:
    rows = []
    for town in towns:
        pose, _ = approach_pose(town, before)
        for wx in weathers:
            ims = Renderer(town, get_weather(wx, family), seed=seed).render(*pose, t=t)
            rows.append((f"{town.name}\n{wx}", ims))
    return _grid(rows, scale, f"{before:.0f} m before a junction (camera to junction entry), {family} weathers")


def turn_sheet(towns: list, weathers: list[str], scale: int = 1, seed: int = 0,
               family: str = DEFAULT_FAMILY) -> np.ndarray:
    rows = []
    for town in towns:
        _, route = approach_pose(town, command=3)
        s_entry, s_exit = route.turns[0][2], route.turns[0][3]
        pose = pose_on_route(route, 0.5 * (s_entry + s_exit) - MOUNT_FORWARD)
        for wx in weathers:
            ims = Renderer(town, get_weather(wx, family), seed=seed).render(*pose, t=0.3)
            rows.append((f"{town.name}\n{wx}", ims))
    return _grid(rows, scale, f"in the middle of a left turn, {family} weathers")


def town_map(town, routes=(), px_per_m: float = 2.5, weather: str = "ClearNoon") -> np.ndarray:
    """Top-down RGB map from the ground texture, with buildings, props and routes by command."""
    r = Renderer(town, weather, cameras=("centre",))
    base = r.ground.base
    lvl = int(np.clip(round(math.log2(1 / (base.res * px_per_m))), 0, len(r.ground.pyramid) - 1))
    img = np.ascontiguousarray(r.ground.pyramid[lvl][..., :3])
    f = 1 / (base.res * 2 ** lvl)  # px per metre

    def px(p):
        p = np.asarray(p, float).reshape(-1, 2)
        return np.round(np.stack([(p[:, 0] - base.x0) * f - 0.5, (base.y1 - p[:, 1]) * f - 0.5], 1) * 16
                        ).astype(np.int32)

    st = town.style
    for b in town.buildings:
        col = tuple(int(v * 0.9) for v in st.facades[b.facade % len(st.facades)])
        cv2.fillPoly(img, [px(b.footprint)], col, cv2.LINE_AA, 4)
        cv2.polylines(img, [px(b.footprint)], True, (40, 40, 40), 1, cv2.LINE_AA, 4)
    for p in town.props:
        c = tuple(int(v) for v in px(p.position)[0])
        if p.kind == "tree":
            cv2.circle(img, c, int(p.radius * f * 16), tuple(int(v * 0.8) for v in st.vegetation), -1, cv2.LINE_AA, 4)
        else:
            cv2.circle(img, c, int(0.4 * f * 16), (30, 30, 30), -1, cv2.LINE_AA, 4)
    for route in routes:
        pts, cmd = px(route.points), np.asarray(route.commands)
        cv2.polylines(img, [pts], False, (20, 20, 20), 4, cv2.LINE_AA, 4)  # outline
        cut = np.nonzero(np.diff(cmd))[0] + 1
        for a, b in zip(np.r_[0, cut], np.r_[cut, len(cmd)]):
            seg = pts[max(a - 1, 0):b]
            cv2.polylines(img, [seg], False, COMMAND_STYLE[int(cmd[a])][1], 2, cv2.LINE_AA, 4)
        s, g = tuple(int(v) for v in pts[0]), tuple(int(v) for v in pts[-1])
        cv2.circle(img, s, 5 * 16, (255, 255, 255), -1, cv2.LINE_AA, 4)
        cv2.circle(img, s, 5 * 16, (0, 0, 0), 1, cv2.LINE_AA, 4)
        cv2.drawMarker(img, (g[0] // 16, g[1] // 16), (0, 0, 0), cv2.MARKER_TILTED_CROSS, 10, 2)
    # legend
    y = 16
    cv2.rectangle(img, (4, 4), (112, 14 + 16 * len(COMMAND_STYLE)), (235, 235, 235), -1)
    for code, (name, col) in COMMAND_STYLE.items():
        cv2.line(img, (10, y), (30, y), (20, 20, 20), 5, cv2.LINE_AA)
        cv2.line(img, (10, y), (30, y), col, 3, cv2.LINE_AA)
        _label(img, f"{code} {name}", (36, y + 4), 0.4)
        y += 16
    _label(img, f"{town.name}: o start, x goal; 10 m = {10 * f:.0f} px", (4, img.shape[0] - 6), 0.45, (255, 255, 255))
    return img


def sample_routes(town, n: int, seed: int = 0, min_length: float = 150.0) -> list:
    """``n`` random routes of the town (helper A's router), balanced over commands."""
    g = road_graph(town)
    rng = np.random.default_rng(seed)
    counts: dict = {}
    return [g.random_route(rng, min_length, name=f"{town.name}/preview{k}", counts=counts) for k in range(n)]


def load_towns(names: list[str]) -> list:
    """Towns by shipped name or file path; a ValueError (one line) for an unknown name, a missing file
    ("no such town file"), a broken one (the file and its problem) or a town listed twice (by any name)."""
    backend = EmbeddedBackend()
    towns = [load_town(backend.resolve_town(n)) for n in names]
    refuse_twice("--towns", [t.name for t in towns])
    return towns


def refuse_twice(option: str, values: list[str]) -> None:
    """A town or weather listed twice would be drawn twice: one line naming the option, as collect's."""
    twice = [v for i, v in enumerate(values) if v in values[:i]]
    if twice:
        raise ConfigError(option, twice[0], "", message=f"{option} lists {twice[0]!r} twice; give each once")


def check_weathers(weathers: list[str], family: str = DEFAULT_FAMILY) -> list[str]:
    if family not in WEATHER_FAMILIES:  # named as this command's option, not as a run's sim.weather_family
        raise CicfwError(f"--weather-family: unknown weather family {family!r}; known: {', '.join(WEATHER_FAMILIES)}",
                         key="--weather-family", value=family)
    presets = WEATHER_FAMILIES[family]
    refuse_twice("--weathers", weathers)
    for wx in weathers:
        if wx not in presets:
            raise CicfwError(f"--weathers: unknown weather {wx!r}; known weathers: {', '.join(presets)}")
    return weathers


def main(argv: list[str] | None = None) -> int:
    """The command line; every bad value is one line (``cicfw: error: ...``, exit status 2)."""
    return report_user_errors(_main)(argv)


def _main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m cicfw.sim.preview", description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="sim_preview", help="output folder (created; default: %(default)s)")
    ap.add_argument("--towns", nargs="+", default=None, help=f"towns (default: all shipped: {town_names()})")
    ap.add_argument("--weathers", nargs="+", default=list(WEATHERS), help="weathers (default: all)")
    ap.add_argument("--weather-family", default=DEFAULT_FAMILY,
                    help=f"the weathers' presets, as a run's sim.weather_family: {' | '.join(WEATHER_FAMILIES)} "
                         f"(default: %(default)s)")
    ap.add_argument("--scale", type=int, default=2, help="image upscale in the sheets (default: %(default)s)")
    ap.add_argument("--routes", type=int, default=4, help="routes drawn on each map (default: %(default)s)")
    ap.add_argument("--seed", type=int, default=0, help="seed of the images and the maps' routes, >= 0 (default: 0)")
    ap.add_argument("--colours", type=int, default=0,
                    help="quantise the PNGs to this many colours (e.g. 256 for small files; default: full colour)")
    ap.add_argument("--prefix", default="", help="prefix of the file names (e.g. sim_)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace files of the pictures' names that no preview wrote (a preview's own are replaced anyway)")
    a = ap.parse_args(argv)
    check_args(a)
    towns = load_towns(a.towns or town_names())
    out = Path(a.out).expanduser().resolve()
    new_top = _first_missing(out)
    # another app's run or a dataset is not a place for pictures of the same names (an evaluation's map_town_a.png
    # of its driven paths); a folder of plain files, an earlier preview's among them, is
    claim_folder(out, "preview", "--out", foreign_ok=True)
    writable_folder(out, "--out", OUT_FOLDER, "--out")  # before the seconds of rendering
    check_overwrites(out, picture_names(a.prefix, towns), a.overwrite)
    try:  # every picture is made, then all are written or none: a late failure leaves no half set of PNGs
        images = _render(a, towns)
        write_together((out / name, marked_png(_png(rgb, a.colours))) for name, rgb in images.items())
    except BaseException as err:
        _remove_empty_folders(out, new_top)
        if isinstance(err, OSError):
            raise CicfwError(f"cannot write {err.filename} ({err.strerror or err}); give a writable --out "
                             f"folder") from None
        raise
    for name in images:
        print(out / name)
    return 0


def _render(a: argparse.Namespace, towns: list) -> dict[str, np.ndarray]:
    """The PNGs' file names -> their RGB images: the two sheets and a map per town."""
    turn_weathers = [w for w in ("ClearNoon", "WetCloudySunset") if w in a.weathers] or a.weathers[:2]
    pictures = [contact_sheet(towns, a.weathers, a.scale, a.seed, family=a.weather_family),
                turn_sheet(towns, turn_weathers, a.scale, a.seed, a.weather_family),
                *(town_map(town, sample_routes(town, a.routes, a.seed)) for town in towns)]
    return dict(zip(picture_names(a.prefix, towns), pictures))


def _first_missing(path: Path) -> Path | None:
    """The topmost folder of ``path`` that does not exist yet (what creating it would create), or None."""
    missing = None
    while not path.exists() and path != path.parent:
        missing, path = path, path.parent
    return missing


def _remove_empty_folders(out: Path, top: Path | None) -> None:
    """Remove the folders this run created (``out`` up to ``top``) while they are empty: a failed run leaves none."""
    if top is None:
        return
    d = out
    while True:
        try:
            d.rmdir()
        except OSError:
            return
        if d == top:
            return
        d = d.parent


def check_args(a: argparse.Namespace) -> None:
    """One ValueError for the first argument outside its domain, before anything is rendered or written."""
    check_weathers(a.weathers, a.weather_family)
    if a.scale < 1:
        raise CicfwError(f"--scale must be >= 1, got {a.scale}")
    if not (a.colours == 0 or 2 <= a.colours <= 256):
        raise CicfwError(f"--colours must be 0 (full colour) or 2..256, got {a.colours}")
    if a.routes < 0:
        raise CicfwError(f"--routes must be >= 0, got {a.routes}")
    if a.seed < 0:
        raise CicfwError(f"--seed must be an integer >= 0 (the seed of the images and of the maps' routes), "
                         f"got {a.seed}")
    check_prefix(a.prefix)


def check_prefix(prefix: str) -> None:
    """``--prefix`` starts file names: a '/' in it would write outside ``--out``."""
    if "/" in prefix or os.sep in prefix:
        raise CicfwError(f"--prefix is the start of the PNGs' file names and takes no '/' (e.g. sim_), got "
                         f"{prefix!r}; choose their folder with --out", key="--prefix", value=prefix)


if __name__ == "__main__":
    from cicfw.core.errors import install_app_handlers
    from cicfw.core.hydra_plugins import guard_hydra_plugins

    install_app_handlers()

    guard_hydra_plugins()  # a plugin whose Hydra module fails to import: one warning, not a stopped app
    sys.exit(main())
