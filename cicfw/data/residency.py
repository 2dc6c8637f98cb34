"""Where a dataset's images live while training: in RAM, or read from the files per batch.

``data.in_memory=auto`` decides by size: the decoded images go to RAM when they take at most
``RAM_SHARE`` of the memory available now, counting one copy per training process on this node (DDP
ranks each load their own; DataLoader workers are forked and share the parent's copy). Otherwise they
are streamed, which costs no memory and delivers more samples per second than a 2-core step trains.
"""
from __future__ import annotations

import os
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
    """Memory this process can still take: MemAvailable, capped by the cgroup's limit if one is set."""
    found = []
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                found.append(int(line.split()[1]) * 1024)
    except OSError:
        pass
    try:
        limit = Path("/sys/fs/cgroup/memory.max").read_text().strip()
        used = int(Path("/sys/fs/cgroup/memory.current").read_text())
        if limit != "max":
            found.append(int(limit) - used)
    except (OSError, ValueError):
        pass
    if not found:  # not Linux: the physical memory, which is all we can know
        found.append(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    return max(0, min(found))


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

    @property
    def needed(self) -> int:
        return self.frames * BYTES_PER_FRAME * self.copies

    def arithmetic(self) -> str:
        per_rank = f" x {self.copies} processes on this node" if self.copies > 1 else ""
        return (f"{self.frames:,} frames x {BYTES_PER_FRAME:,} bytes{per_rank} = {gb(self.needed)} against "
                f"{gb(self.available)} available")

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
    available = available_bytes() if available is None else available
    need = frames * BYTES_PER_FRAME * copies
    if setting == "auto":
        return Residency(need <= RAM_SHARE * available, frames, copies, available, setting)
    if setting and need > available:
        plan = Residency(True, frames, copies, available, setting)
        raise CicfwError(f"data.in_memory=true cannot hold these images: {plan.arithmetic()}; use "
                         f"data.in_memory=auto (streams what does not fit) or false")
    return Residency(bool(setting), frames, copies, available, setting)
