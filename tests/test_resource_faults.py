"""Resource and file faults in one line: the address-space limit counted by ``data.in_memory=auto``, a corrupt
file named as corrupt, a filter that drops most rows saying so, the quoting hint only when a space is the
cause, every JSON read naming its file, every refusal naming its key."""
from __future__ import annotations

import json
import logging
import math
import resource
from pathlib import Path

import h5py
import numpy as np
import pytest

from cicfw.core.errors import CicfwError, ConfigError
from cicfw.testing import make_targets, write_tiny_dataset

# ---- the address-space limit (ulimit -v) ------------------------------------------------------------------


def _limited(monkeypatch, room: int) -> None:
    """RLIMIT_AS set ``room`` bytes above what this process maps now; the other limits as they are."""
    from cicfw.data import residency

    real = resource.getrlimit
    limit = residency.address_space_used() + room

    def getrlimit(which: int):
        return (limit, limit) if which == resource.RLIMIT_AS else real(which)

    monkeypatch.setattr(residency.resource, "getrlimit", getrlimit)


def test_in_memory_auto_counts_the_address_space_limit(monkeypatch):
    from cicfw.data.residency import BYTES_PER_FRAME, decide

    frames = 1000  # 53 MB of images: nothing against the machine's memory, more than half of 60 MB of room
    assert decide(frames, "auto").in_memory  # unlimited: in RAM
    _limited(monkeypatch, 60 * 10**6)
    plan = decide(frames, "auto")
    assert not plan.in_memory and plan.available <= 60 * 10**6 < 2 * frames * BYTES_PER_FRAME
    assert "ulimit -v" in plan.reason()  # the log line says what bounds the memory
    with pytest.raises(CicfwError) as err:
        decide(2000, True)
    assert err.value.key == "data.in_memory"
