"""Reading back the JSON files cicfw writes (cell.json, reproduce.json, a dataset's metadata ...): a file
that is not valid JSON is one line naming it, where json's own message says only where in the text.
"""
from __future__ import annotations

import json
import os
import stat
from pathlib import Path
from typing import Any

from cicfw.core.errors import CicfwError

_NO_DEFAULT: Any = object()


def read_json(path: str | os.PathLike, default: Any = _NO_DEFAULT, kind: type | None = None) -> Any:
    """The JSON value in ``path``; ``default``, when given, for a file that does not exist. A file that is not
    valid JSON (truncated by a kill or a full disk, edited by hand) or cannot be read is one ``CicfwError``
    naming it: json's own message says where in the text, not which file. ``kind`` (``dict``): the value must
    be one, else the same error, so that a record holding ``null`` is not read as a missing one."""
    path = Path(path)
    try:
        if not stat.S_ISREG(path.stat().st_mode):  # a FIFO would block the read forever, a device never end
            raise CicfwError(f"{path}: not a regular file, where a JSON record belongs; replace it with the record "
                             f"or remove it")
        text = path.read_text()
    except FileNotFoundError:
        if default is not _NO_DEFAULT:
            return default
        raise
    except UnicodeDecodeError:
        raise CicfwError(f"{path}: not valid JSON (not UTF-8 text)") from None
    except OSError as err:
        raise CicfwError(f"{path}: cannot be read ({err.strerror or err})") from None
    try:
        value = json.loads(text)
    except json.JSONDecodeError as err:
        raise CicfwError(f"{path}: not valid JSON ({err.msg}: line {err.lineno} column {err.colno}); the file "
                         f"is truncated (a kill, a full disk) or was edited by hand") from None
    if kind is not None and not isinstance(value, kind):
        raise CicfwError(f"{path}: holds {json.dumps(value)[:40]} where a JSON "
                         f"{'object' if kind is dict else kind.__name__} belongs; the file was edited by hand or "
                         f"written by something else")
    return value
