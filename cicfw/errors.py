"""User-facing errors: the entry points print these as one clear line instead of a traceback."""
from __future__ import annotations

import functools
import logging
import sys
from typing import Callable, TypeVar

from cicfw.data.cil_hdf5 import CILFormatError
from cicfw.registry import UnknownNameError

# Errors a user causes with a bad file, path, name or value; everything else is a bug and keeps its traceback.
USER_ERRORS: tuple[type[BaseException], ...] = (ValueError, FileNotFoundError, UnknownNameError, CILFormatError)

F = TypeVar("F", bound=Callable)
log = logging.getLogger("cicfw")


def _in_multirun() -> bool:
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    except Exception:
        return False


def report_user_errors(fn: F) -> F:
    """Exit with ``cicfw: error: <message>`` (status 2) on a user error; in a multirun, re-raise so
    the sweep records the job as failed and goes on."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except USER_ERRORS as err:
            if _in_multirun():
                raise
            msg = err.args[0] if isinstance(err, (KeyError, FileNotFoundError)) and err.args else err
            print(f"cicfw: error: {msg}", file=sys.stderr)
            sys.exit(2)

    return wrapper  # type: ignore[return-value]
