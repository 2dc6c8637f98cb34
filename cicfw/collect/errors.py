"""The collection's user errors: each a ``CicfwError``, so every app prints it as one line."""
from __future__ import annotations

from cicfw.core.errors import CicfwError


class CollectError(CicfwError):
    """A collection that cannot go on for a reason the user can fix; the message says what and how."""


class CollectConfigError(CollectError):
    """A bad ``collect`` config value; the message names the key and what is accepted."""


class FolderLockedError(CollectError):
    """The output folder is locked by another collector; the message names the holder."""


class DiskFullError(CollectError):
    """Not enough free space for the next episode, or a write failed with ENOSPC / EDQUOT."""
