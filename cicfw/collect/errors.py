"""The collection's user errors: each a ``ValueError``, so every app prints it as one line."""
from __future__ import annotations


class CollectError(ValueError):
    """A collection that cannot go on for a reason the user can fix; the message says what and how.

    A ``ValueError`` so that the apps' ``report_user_errors`` prints it as one line."""


class CollectConfigError(CollectError):
    """A bad ``collect`` config value; the message names the key and what is accepted."""


class FolderLockedError(CollectError):
    """The output folder is locked by another collector; the message names the holder."""


class DiskFullError(CollectError):
    """Not enough free space for the next episode, or a write failed with ENOSPC / EDQUOT."""
