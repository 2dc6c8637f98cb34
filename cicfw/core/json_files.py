"""Reading back the JSON files cicfw writes (cell.json, reproduce.json, a dataset's metadata ...): a file
that is not valid JSON is one line naming it, where json's own message says only where in the text.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from cicfw.core.errors import CicfwError

_NO_DEFAULT: Any = object()


def read_json(path: str | os.PathLike, default: Any = _NO_DEFAULT) -> Any:
    """The JSON value in ``path``; ``default``, when given, for a file that does not exist. A file that is not
    valid JSON (truncated by a kill or a full disk, edited by hand) or cannot be read is one ``CicfwError``
    naming it: json's own message says where in the text, not which file."""
    path = Path(path)
    try:
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
        return json.loads(text)
    except json.JSONDecodeError as err:
        raise CicfwError(f"{path}: not valid JSON ({err.msg}: line {err.lineno} column {err.colno}); the file "
                         f"is truncated (a kill, a full disk) or was edited by hand") from None
