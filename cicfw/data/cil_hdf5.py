"""The CoRL-2017 CIL HDF5 layout: the one format cicfw reads and writes.

A file holds ``rgb`` uint8 (N, 88, 200, 3) and ``targets`` float32 (N, 28); other datasets
(``depth``, ``labels`` ...) are ignored. The images may also be named ``images_center``, the name the
CoRL-2017 dataset's own README gives them (the files in circulation use ``rgb``; cicfw writes ``rgb``). The ``T`` class names every index of ``targets``.
"""
from __future__ import annotations

import glob
import logging
import io
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from cicfw.core.errors import CicfwError
from cicfw.core.files import atomic_write

log = logging.getLogger(__name__)

IMAGE_SHAPE = (88, 200, 3)  # rows, columns, RGB
N_TARGETS = 28
SAMPLES_PER_FILE = 200
COMMAND_CODES = (2, 3, 4, 5)  # follow, left, right, straight -> branch = code - 2
IMAGE_KEYS = ("rgb", "images_center")  # accepted names of the image dataset, in order of preference
KNOWN_CAMERA_IDS = {0: "centre", 1: "left", 2: "right"}  # targets[26] in files cicfw writes


class T:
    """Indices into ``targets`` (CIL CoRL-2017)."""

    STEER, GAS, BRAKE, HAND_BRAKE, REVERSE = 0, 1, 2, 3, 4
    STEER_NOISE, GAS_NOISE, BRAKE_NOISE = 5, 6, 7
    POS_X, POS_Y = 8, 9
    SPEED = 10  # km/h
    COLLISION_OTHER, COLLISION_PEDESTRIAN, COLLISION_CAR = 11, 12, 13
    OPPOSITE_LANE, SIDEWALK = 14, 15
    ACC_X, ACC_Y, ACC_Z = 16, 17, 18
    PLATFORM_TIME, GAME_TIME = 19, 20
    ORIENT_X, ORIENT_Y, ORIENT_Z = 21, 22, 23
    COMMAND = 24  # 2 follow, 3 left, 4 right, 5 straight
    NOISE_FLAG = 25
    CAMERA_ID = 26  # 0 centre, 1 left, 2 right in files cicfw writes
    CAMERA_YAW = 27  # degrees, positive to the right (left camera -30, right camera +30)


class CILFormatError(CicfwError):
    """A file that is not in the CIL HDF5 layout; the message names the file and the problem."""



class CorruptFileError(CILFormatError):
    """A CIL file whose stored bytes cannot be decoded (a compressed chunk that fails to decompress, a failing
    checksum, a chunk index pointing past the end): damaged when written or since. The message names the
    file first; ``path`` is the file. Raised in a DataLoader worker, it comes back holding the worker's
    traceback in its one argument: the line is taken back out of it."""

    def __init__(self, message: str, path: Path | None = None) -> None:
        marker = f"{type(self).__name__}: "
        last = message.rstrip().splitlines()[-1] if message.strip() else message
        message = last.split(marker, 1)[1] if marker in last else message
        super().__init__(message)
        self.path = Path(path) if path is not None else Path(message.split(": ", 1)[0])


def corrupt_file(path: Path, what: str, err: BaseException) -> CorruptFileError:
    """The one line for ``path`` whose ``what`` (its images, its 'targets') cannot be decoded (``err``)."""
    why = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
    return CorruptFileError(f"{path}: corrupt: {what} cannot be read back ({type(err).__name__}: {why}); the file "
                            f"was damaged when written or since: replace it, or move it out of the data folder",
                            path)


LAYOUT = ("a CIL file needs its images as 'rgb' (or 'images_center') uint8 (N, 88, 200, 3) and "
          "'targets' float32 (N, 28)")


def image_key(f: h5py.File) -> str:
    """The name of the image dataset in an open file: the first of IMAGE_KEYS it holds."""
    for key in IMAGE_KEYS:
        if key in f:
            return key
    raise CILFormatError(
        f"{f.filename}: no image dataset: neither 'rgb' nor 'images_center'; {LAYOUT} "
        f"(found: {', '.join(sorted(f.keys())) or 'nothing'})"
    )


HDF5_SUFFIXES = (".h5", ".hdf5")  # matched in any case: FILE.H5 is an HDF5 file too


def is_hdf5_name(path: Path) -> bool:
    """Whether ``path``'s suffix is an HDF5 one, in any case."""
    return path.suffix.lower() in HDF5_SUFFIXES


def _walk(folder: Path) -> list[Path]:
    """Every entry under ``folder``, following linked folders (as a ``**`` glob does; ``Path.rglob`` does not),
    each real folder once: a link back up the tree is not a loop. A file reached twice is left to
    ``distinct_files``."""
    out, seen = [], set()
    for root, dirs, names in os.walk(folder, followlinks=True):
        st = os.stat(root)
        if (st.st_dev, st.st_ino) in seen:
            dirs[:] = []
            continue
        seen.add((st.st_dev, st.st_ino))
        out += [Path(root) / n for n in [*dirs, *names]]
    return out


def find_files(path: str | os.PathLike | list | tuple) -> list[Path]:
    """HDF5 files under a folder (recursively, linked folders followed as a ``**`` glob follows them; suffixes
    in any case) or matching a glob, sorted (a
    folder's ``.h5`` files, then its ``.hdf5`` ones); error if none. A list is the files themselves, in
    its order (the files a run recorded, ``cicfw.data.provenance``): each must exist."""
    if isinstance(path, (list, tuple)):
        files = [Path(os.path.expanduser(str(f))) for f in path]
        missing = [str(f) for f in files if not f.is_file()]
        if missing or not files:
            raise FileNotFoundError(f"{len(missing)} of the {len(files)} data file(s) given are not there: "
                                    f"{', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''}")
        return files
    p = str(path)
    p = os.path.expanduser(p)
    if os.path.isdir(p):
        named = [f for f in _walk(Path(p)) if is_hdf5_name(f)]
        found = [f for f in named if f.is_file()]
        dangling = sorted(str(f) for f in named if f.is_symlink() and not f.exists())
        if dangling:  # a link whose file is gone: its episodes are missing from the data, say so
            log.warning("%d HDF5 link(s) under %s point at nothing and are skipped: %s", len(dangling), p,
                        ", ".join(dangling[:5]) + (" ..." if len(dangling) > 5 else ""))
        files = [f for suffix in HDF5_SUFFIXES for f in sorted(found) if f.suffix.lower() == suffix]
    else:
        files = sorted(Path(f) for f in glob.glob(p, recursive=True) if os.path.isfile(f))
    if not files:
        raise FileNotFoundError(
            f"data.path={path!r} matches no HDF5 file; give a folder that holds *.h5 / *.hdf5 "
            f"files (searched recursively, suffixes in any case) or a glob such as 'data/**/*.h5'"
        )
    return files


@dataclass
class FileInfo:
    path: Path
    n: int


def _link(f: h5py.File, key: str) -> str:
    """What the entry ``key`` is as a link: a soft or external link's target, else a plain entry."""
    link = f.get(key, getlink=True)
    if isinstance(link, h5py.SoftLink):
        return f"a soft link to {link.path!r}"
    if isinstance(link, h5py.ExternalLink):
        return f"an external link to {link.path!r} in {link.filename!r}"
    return "an entry"


def _dataset(f: h5py.File, key: str, path: Path) -> h5py.Dataset:
    """``f[key]`` when it is a dataset that can be opened; else CILFormatError naming the file, the key
    and what it is (a group, a link that leads nowhere)."""
    try:
        obj = f[key]
    except (KeyError, OSError) as err:
        why = err.args[0] if isinstance(err, KeyError) and err.args else err
        raise CILFormatError(f"{path}: {key!r} is {_link(f, key)} that cannot be opened ({why}); {LAYOUT} "
                             f"that open from the file") from None
    if not isinstance(obj, h5py.Dataset):
        kind = "a group" if isinstance(obj, h5py.Group) else type(obj).__name__
        raise CILFormatError(f"{path}: {key!r} is {kind}, not a dataset; {LAYOUT}")
    return obj


def check_signature(path: Path) -> None:
    """A CILFormatError when ``path`` does not start as an HDF5 file does (h5py reads only its superblock):
    what ``check_file`` would refuse, found before anything reads the whole file (the data record's hash)."""
    try:
        ok = h5py.is_hdf5(str(path))
    except OSError as err:
        raise CILFormatError(f"{path}: not a readable HDF5 file ({err})") from None
    if not ok:
        raise CILFormatError(f"{path}: not a readable HDF5 file (no HDF5 signature)")


def check_file(path: Path) -> FileInfo:
    """Open ``path`` and check it is in the CIL layout; raise CILFormatError naming what is wrong."""
    try:
        f = h5py.File(path, "r")
    except OSError as err:
        raise CILFormatError(f"{path}: not a readable HDF5 file ({err})") from None
    with f:
        key = image_key(f)
        if "targets" not in f:
            raise CILFormatError(
                f"{path}: no 'targets' dataset; {LAYOUT} (found: {', '.join(sorted(f.keys()))})"
            )
        rgb, targets = _dataset(f, key, path), _dataset(f, "targets", path)
        if rgb.ndim != 4 or tuple(rgb.shape[1:]) != IMAGE_SHAPE or rgb.dtype != np.uint8:
            raise CILFormatError(
                f"{path}: {key!r} is {rgb.dtype} {tuple(rgb.shape)}; expected uint8 (N, 88, 200, 3)"
            )
        if targets.ndim != 2 or targets.shape[1] != N_TARGETS or targets.dtype.kind != "f":
            raise CILFormatError(
                f"{path}: 'targets' is {targets.dtype} {tuple(targets.shape)}; expected float32 (N, 28)"
            )
        if rgb.shape[0] != targets.shape[0]:
            raise CILFormatError(
                f"{path}: {key!r} has {rgb.shape[0]} samples but 'targets' has {targets.shape[0]}"
            )
        return FileInfo(path, int(rgb.shape[0]))


def read_targets(path: Path) -> np.ndarray:
    """The file's ``targets`` as float32; a ``CorruptFileError`` naming it when they cannot be decoded."""
    with h5py.File(path, "r") as f:
        try:
            return np.asarray(f["targets"], dtype=np.float32)
        except OSError as err:  # h5py's "filter returned failure" names no file
            raise corrupt_file(path, "its 'targets'", err) from None


def read_rgb(path: Path) -> np.ndarray:
    """All images of a file, whichever accepted name (IMAGE_KEYS) their dataset has."""
    with h5py.File(path, "r") as f:
        return np.asarray(f[image_key(f)])


def file_bytes(rgb: np.ndarray, targets: np.ndarray) -> bytes:
    """One CIL file built in memory (``rgb`` chunked per image, as the public files): what
    ``write_file`` writes and what the collector writes with its episode's other files."""
    rgb = np.ascontiguousarray(rgb, dtype=np.uint8)
    targets = np.ascontiguousarray(targets, dtype=np.float32)
    if rgb.ndim != 4 or rgb.shape[1:] != IMAGE_SHAPE:
        raise ValueError(f"rgb must be (N, 88, 200, 3), got {rgb.shape}")
    if targets.shape != (rgb.shape[0], N_TARGETS):
        raise ValueError(f"targets must be ({rgb.shape[0]}, 28), got {targets.shape}")
    bio = io.BytesIO()
    with h5py.File(bio, "w") as f:
        f.create_dataset("rgb", data=rgb, chunks=(1, *IMAGE_SHAPE))
        f.create_dataset("targets", data=targets)
    return bio.getvalue()


def write_file(path: str | os.PathLike, rgb: np.ndarray, targets: np.ndarray) -> Path:
    """Write one CIL file atomically (temporary name in the same folder, then rename), with the umask's
    mode: a dataset is meant to be shared."""
    path = Path(path)
    atomic_write(path, file_bytes(rgb, targets))
    return path
