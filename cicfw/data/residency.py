"""Where a dataset's images live while training: in RAM, or read from the files per batch.

``data.in_memory=auto`` decides by size: the decoded images go to RAM when they take at most
``RAM_SHARE`` of the memory available now (the machine's, the cgroup's, and the room a per-process limit
such as ``ulimit -v`` leaves), counting one copy per training process on this node (DDP ranks each load
their own; DataLoader workers are forked and share the parent's copy). Otherwise they
are streamed, which costs no memory and delivers more samples per second than a 2-core step trains.
"""
from __future__ import annotations

import os
import resource
from dataclasses import dataclass
from pathlib import Path

from cicfw.core.errors import CicfwError, ConfigError
from cicfw.data.cil_hdf5 import IMAGE_SHAPE

#: Share of the available memory the images may take: the rest is for the model, its optimizer and
#: activations, the workers' batches and the page cache the validation reads go through.
RAM_SHARE = 0.5
BYTES_PER_FRAME = IMAGE_SHAPE[0] * IMAGE_SHAPE[1] * IMAGE_SHAPE[2]  # uint8 RGB, 52,800 bytes
ACCEPTED = "true (RAM), false (streamed from the files) or auto (RAM when the images fit, else streamed)"


def in_memory_setting(value: object) -> bool | str:
    """``data.in_memory`` as True, False or ``"auto"``; anything else is one line naming the key."""
    if isinstance(value, bool) or value == "auto":
        return value
    raise ConfigError("data.in_memory", value, ACCEPTED)


def available_bytes() -> int:
    """Memory this process can still take: MemAvailable, capped by the cgroup's limit and by the room a
    per-process limit leaves (``process_limits``: ``ulimit -v`` counts the address space, not the memory)."""
    memory = _status_bytes("MemAvailable", "/proc/meminfo")
    found = [memory] if memory else []
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = int(Path("/sys/fs/cgroup/memory.current").read_text())
        if limit != "max":
            found.append(int(limit) - used)
    except (OSError, ValueError):
        pass
    if not found:  # not Linux: the physical memory, which is all we can know
        found.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    found += [room for room, _ in process_limits()]
    return max(0, min(found))


#: the per-process limits a large array can meet before the machine's memory runs out: the limit, the
#: line of /proc/self/status that says what it counts now, and its name (``ulimit -v``: common on clusters)
LIMITS = ((resource.RLIMIT_AS, "VmSize", "ulimit -v, the address-space limit"),
          (resource.RLIMIT_DATA, "VmData", "ulimit -d, the data-segment limit"))


def _status_bytes(field: str, path: str = "/proc/self/status") -> int:
    """A size line of /proc/self/status (``VmSize``: the address space this process maps now) or of ``path``
    (/proc/meminfo's ``MemAvailable``), in bytes; 0 where there is none."""
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return 0


def process_limits() -> list[tuple[int, str]]:
    """(room left, what it is) for each per-process memory limit set (``ulimit -v``, ``ulimit -d``): an
    array beyond the room fails to allocate (numpy's ``_ArrayMemoryError``) however much the machine has."""
    out = []
    for which, field, name in LIMITS:
        soft = resource.getrlimit(which)[0]
        if soft != resource.RLIM_INFINITY and soft >= 0:
            used = _status_bytes(field)
            out.append((max(0, soft - used), f"{name}: {gb(soft)}, {gb(used)} of it in use"))
    return out


def limit_note() -> str:
    """What bounds the memory when a per-process limit leaves less room than any other: `` (<limit>)``."""
    limits = process_limits()
    if not limits:
        return ""
    room, name = min(limits)
    return f" ({name})" if room <= available_bytes() else ""


def gb(n: float) -> str:
    return f"{n / 1e9:.1f} GB"


@dataclass(frozen=True)
class Residency:
    """The decision and the arithmetic behind it, said in one log line."""

    in_memory: bool
    frames: int
    copies: int  # training processes on this node, each holding its own copy in RAM
    available: int
    setting: bool | str
    bound: str = ""  # `` (ulimit -v, the address-space limit ...)`` when such a limit bounds ``available``

    @property
    def needed(self) -> int:
        return self.frames * BYTES_PER_FRAME * self.copies

    def arithmetic(self) -> str:
        per_rank = f" x {self.copies} processes on this node" if self.copies > 1 else ""
        return (f"{self.frames:,} frames x {BYTES_PER_FRAME:,} bytes{per_rank} = {gb(self.needed)} against "
                f"{gb(self.available)} available{self.bound}")

    def reason(self) -> str:
        where = "in RAM" if self.in_memory else "streamed from the files"
        if self.setting != "auto":
            return f"data: images {where} (data.in_memory={str(self.setting).lower()}; {self.arithmetic()})"
        rule = "within" if self.in_memory else "more than"
        return (f"data: images {where} (data.in_memory=auto: {self.arithmetic()}, {rule} the "
                f"{RAM_SHARE:.0%} kept for them)")


def decide(frames: int, setting: bool | str, copies: int = 1, available: int | None = None) -> Residency:
    """RAM or streamed for ``frames`` images; ``in_memory=true`` on images that cannot fit in the memory
    available at all is refused here, before any image is read, with the arithmetic."""
    bound = limit_note() if available is None else ""
    available = available_bytes() if available is None else available
    need = frames * BYTES_PER_FRAME * copies
    if setting == "auto":
        return Residency(need <= RAM_SHARE * available, frames, copies, available, setting, bound)
    if setting and need > available:
        plan = Residency(True, frames, copies, available, setting, bound)
        raise CicfwError(f"data.in_memory=true cannot hold these images: {plan.arithmetic()}; use "
                         f"data.in_memory=auto (streams what does not fit) or false", key="data.in_memory", value=True)
    return Residency(bool(setting), frames, copies, available, setting, bound)
