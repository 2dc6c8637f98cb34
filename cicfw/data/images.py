"""ImageStore: the images of a Frames table, in RAM (one uint8 array) or read from the files per batch.

Streaming reads an image where its bytes lie: for images stored uncompressed (the CoRL-2017 files and
cicfw's own: one chunk per image, no filter) the byte offsets are read once per file from HDF5's chunk
index and each image is then one ``pread``, several times faster than h5py's selection machinery for
single rows; compressed images go through h5py. Files stay open between batches, at most
``MAX_OPEN_FILES`` per process: half of its open-file limit, since a public-size dataset has thousands
of files, more than many systems let a process open. It checks, at each read (one ``stat``, microseconds against
milliseconds of reading), that a file is still the one whose labels were read at setup: a file replaced,
shrunk or removed mid-run stops the run with one line naming it, never images paired with other labels
(HDF5 reads past the end of a shrunk file as zeros, without an error). An unchanged file whose images
cannot be read back (a compressed chunk that fails to decompress) is named as corrupt.
"""
from __future__ import annotations

import os
import resource
from collections import OrderedDict
from pathlib import Path

import h5py
import numpy as np

from cicfw.core.errors import CicfwError
from cicfw.data.cil_hdf5 import IMAGE_SHAPE, CorruptFileError, corrupt_file, image_key
from cicfw.data.frames import Frames

MAX_OPEN_FILES = max(64, resource.getrlimit(resource.RLIMIT_NOFILE)[0] // 2)
FRAME_BYTES = int(np.prod(IMAGE_SHAPE))


class DataChangedError(CicfwError):
    """A data file changed or vanished after setup; the message names it."""

    def __init__(self, message: str) -> None:
        # A DataLoader worker's error comes back with the worker's traceback in its message: keep our line.
        marker = f"{type(self).__name__}: "
        last = message.rstrip().splitlines()[-1] if message.strip() else message
        super().__init__(last.split(marker, 1)[1] if marker in last else message)


def identity(path: Path) -> tuple[int, int, int]:
    """What says a file is still the one read at setup: inode, size, modification time."""
    st = os.stat(path)
    return st.st_ino, st.st_size, st.st_mtime_ns


class FileImages:
    """The image rows of one file: ``pread`` at byte offsets where they are stored raw, else h5py."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.h5: h5py.File | None = h5py.File(path, "r", rdcc_nbytes=0)
        self.offsets = raw_offsets(self.h5[image_key(self.h5)])
        self.fd: int | None = None
        if self.offsets is not None:  # the HDF5 handle is no longer needed: one descriptor per file
            self.h5.close()
            self.h5, self.fd = None, os.open(path, os.O_RDONLY)

    def read(self, rows: np.ndarray, out: np.ndarray) -> None:
        """Rows ``rows`` (increasing) into ``out``."""
        if self.fd is None:  # h5py wants strictly increasing rows: read each once, then repeat
            unique, back = np.unique(rows, return_inverse=True)
            out[:] = self.h5[image_key(self.h5)][unique][back]
            return
        for i, r in enumerate(rows):
            got = os.preadv(self.fd, [out[i]], int(self.offsets[r]))
            if got != FRAME_BYTES:
                raise OSError(f"read {got} of {FRAME_BYTES} bytes of row {int(r)}: the file is shorter than its index")

    def close(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
        elif self.h5 is not None:
            self.h5.close()


def raw_offsets(ds: h5py.Dataset) -> np.ndarray | None:
    """Byte offset of each image row where the images are stored unfiltered, one row per chunk or
    contiguous; None otherwise (compressed, or another chunk shape)."""
    plist = ds.id.get_create_plist()
    if plist.get_nfilters():
        return None
    if ds.chunks is None:
        start = ds.id.get_offset()
        return None if start is None else start + np.arange(ds.shape[0], dtype=np.int64) * FRAME_BYTES
    if tuple(ds.chunks) != (1, *IMAGE_SHAPE) or ds.id.get_num_chunks() != ds.shape[0]:
        return None
    offsets = np.empty(ds.shape[0], np.int64)
    ds.id.chunk_iter(lambda info: offsets.__setitem__(info.chunk_offset[0], info.byte_offset))
    return offsets


class ImageStore:
    """Images by frame index, from RAM or from the files (``in_memory``)."""

    def __init__(self, frames: Frames, in_memory: bool) -> None:
        self.frames = frames
        self.array: np.ndarray | None = None
        self._handles: OrderedDict[int, FileImages] = OrderedDict()
        self._owner = os.getpid()
        used = np.unique(frames.file_idx)
        self._identity = {int(fi): identity(frames.files[fi]) for fi in used} if not in_memory else {}
        if in_memory:
            self.array = np.empty((len(frames), *IMAGE_SHAPE), np.uint8)
            for fi in used:
                where = np.flatnonzero(frames.file_idx == fi)
                with h5py.File(frames.files[fi], "r") as f:
                    try:
                        self.array[where] = f[image_key(f)][()][frames.row[where]]
                    except OSError as err:  # h5py's "filter returned failure" names no file
                        raise corrupt_file(frames.files[fi], "its images", err) from None

    def get(self, idx: np.ndarray) -> np.ndarray:
        if self.array is not None:
            return self.array[idx]  # fancy indexing copies, so augmentation never edits the store
        out = np.empty((len(idx), *IMAGE_SHAPE), np.uint8)
        fidx, rows = self.frames.file_idx[idx], self.frames.row[idx]
        for fi in np.unique(fidx):
            sel = np.flatnonzero(fidx == fi)
            order = np.argsort(rows[sel])  # h5py wants increasing row indices
            path = self.frames.files[fi]
            try:
                block = np.empty((len(sel), *IMAGE_SHAPE), np.uint8)
                self._open(int(fi)).read(rows[sel][order], block)
                out[sel[order]] = block
            except (DataChangedError, CorruptFileError):
                raise
            except (OSError, KeyError, IndexError, ValueError) as err:
                self._check(int(fi))  # the file changed or vanished since setup: that line, else it is damaged
                raise corrupt_file(path, "its images", err) from None
        return out

    def _open(self, fi: int) -> FileImages:
        """An open handle on file ``fi``, checked against its setup identity; least recently used handles
        are closed beyond MAX_OPEN_FILES."""
        if os.getpid() != self._owner:  # a forked worker: the parent's HDF5 handles are not ours to use
            self._handles, self._owner = OrderedDict(), os.getpid()
        self._check(fi)
        if fi in self._handles:
            self._handles.move_to_end(fi)
            return self._handles[fi]
        while len(self._handles) >= MAX_OPEN_FILES:
            self._handles.popitem(last=False)[1].close()
        self._handles[fi] = FileImages(self.frames.files[fi])
        return self._handles[fi]

    def _check(self, fi: int) -> None:
        """File ``fi`` is still the one whose labels were read at setup, or one line naming it."""
        path = self.frames.files[fi]
        try:
            now = identity(path)
        except OSError:
            raise DataChangedError(f"{path}: removed after the run started; its labels were read at setup, "
                                   f"so the run cannot go on (its checkpoints so far are kept)") from None
        if now != self._identity[fi]:
            raise DataChangedError(f"{path}: replaced or rewritten after the run started (size, inode or "
                                   f"modification time changed): its images would not match the labels read "
                                   f"at setup; restore it or start the run again")

    def __getstate__(self) -> dict:  # open HDF5 handles do not cross into worker processes
        return {**self.__dict__, "_handles": OrderedDict()}
