"""User-facing errors: the entry points print these as one clear line instead of a traceback."""
from __future__ import annotations

import functools
import logging
import math
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


class NonFiniteResult(ArithmeticError):
    """A multirun job returned nan/inf: sweepers cannot rank it (Optuna would stop), so it fails."""


def _message(err: BaseException) -> object:
    return err.args[0] if isinstance(err, (KeyError, FileNotFoundError)) and err.args else err


def report_user_errors(fn: F) -> F:
    """Exit with ``cicfw: error: <message>`` (status 2) on a user error.

    In a multirun every failure is logged to the job's log and re-raised, so Hydra marks the job
    FAILED: the sweep summary records it with its error and the other jobs go on (all jobs of a
    batch run; the Optuna sweeper marks the trial failed). A non-finite result (a diverged training)
    fails the job the same way instead of reaching the sweeper.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        multirun = _in_multirun()
        try:
            result = fn(*args, **kwargs)
        except USER_ERRORS as err:
            if multirun:
                log.error("job failed: %s", _message(err))
                raise
            print(f"cicfw: error: {_message(err)}", file=sys.stderr)
            sys.exit(2)
        except Exception:
            if multirun:
                log.exception("job failed")
            raise
        if multirun and isinstance(result, float) and not math.isfinite(result):
            err = NonFiniteResult(f"the job's result is {result} (training diverged, or no validation ran)")
            log.error("job failed: %s", err)
            raise err
        return result

    return wrapper  # type: ignore[return-value]
