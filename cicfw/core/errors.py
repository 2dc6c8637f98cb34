"""The error family a user can fix (``CicfwError``), and how an app ends: one line for a user error or a stop.

A ``CicfwError`` (``ConfigError`` for one config key) is what a user's input caused and the user can fix:
an app prints it as one ``cicfw: error: <message>`` line and exits with status 2. Anything else is a bug
and keeps its traceback. ``CICFW_DEBUG=1`` prints the traceback of a user error too. The handlers for
SIGTERM and uncaught exceptions are installed by an app's ``main`` (``install_app_handlers``), never by
importing a module.
"""
from __future__ import annotations

import atexit
import errno
import functools
import logging
import math
import os
import signal
import sys
import threading
import traceback
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import Any, Callable, Iterator, TypeVar

#: set to 1 to see the traceback of a user error too
DEBUG_VARIABLE = "CICFW_DEBUG"


class CicfwError(ValueError):
    """Something a user's input caused and the user can fix (a bad file, path, name or value); the message
    says what and how. ``key`` and ``value``: the config key (``mixer.gate_bias``) and the value refused,
    where there is one. A ``ValueError``, so code that catches ``ValueError`` still catches it."""

    key: str | None = None
    value: Any = None

    def __init__(self, *args: Any, key: str | None = None, value: Any = None) -> None:
        super().__init__(*args)
        if key is not None:
            self.key = key
        if value is not None:
            self.value = value


class ConfigError(CicfwError):
    """A config value the code refuses: ``ConfigError("model.lr", -1, "a number > 0")`` reads
    ``model.lr must be a number > 0, got -1``; ``message`` replaces that sentence where it says more (it
    should still name the key and the value)."""

    def __init__(self, key: str, value: Any, accepted: str, message: str | None = None) -> None:
        super().__init__(message or f"{key} must be {accepted}, got {value!r}", key=key, value=value)
        self.key, self.value, self.accepted = key, value, accepted

    def __reduce__(self) -> tuple:  # a multirun launcher may pickle a job's error
        return type(self), (self.key, self.value, self.accepted, str(self))


# Errors a user causes (a missing file the user named is one); everything else is a bug and keeps its traceback.
USER_ERRORS: tuple[type[BaseException], ...] = (CicfwError, FileNotFoundError)


def debugging() -> bool:
    """Whether ``CICFW_DEBUG`` asks for the traceback of a user error too."""
    return os.environ.get(DEBUG_VARIABLE, "") not in ("", "0")

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


class Interrupted(KeyboardInterrupt):
    """Ctrl-C, with what was kept and how to go on (``cicfw: interrupted; <message>``)."""


@contextmanager
def on_interrupt(message: str) -> Iterator[None]:
    """A Ctrl-C inside becomes ``Interrupted(message)``: what this stage leaves kept, how to go on."""
    try:
        yield
    except Interrupted:
        raise
    except KeyboardInterrupt:
        raise Interrupted(message) from None


#: the signal that stopped the app, when it was not Ctrl-C (SIGTERM: a scheduler, ``timeout``, ``kill``)
_stopped_by: int | None = None


def _interrupting_handler(owner: int) -> Callable[[int, object], None]:
    """A SIGTERM handler raising KeyboardInterrupt in process ``owner`` (recording the signal for the
    one line); a forked child that inherited it (a DataLoader worker) dies of SIGTERM as usual."""

    def stop(signum: int, frame: object) -> None:
        global _stopped_by
        if os.getpid() != owner:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)
            os.kill(os.getpid(), signal.SIGTERM)
            return
        _stopped_by = signum
        raise KeyboardInterrupt

    return stop


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """Inside, SIGTERM raises KeyboardInterrupt in this process, as Ctrl-C does, so every stage cleans up
    and says what it kept; the previous handler is back afterwards. A forked child (a DataLoader worker)
    that inherits the handler dies of SIGTERM as usual. Off the main thread it does nothing."""
    global _stopped_by
    if threading.current_thread() is not threading.main_thread() or signal.getsignal(signal.SIGTERM) is None:
        yield  # signals go to the main thread only; None: a handler Python cannot put back
        return
    _stopped_by = None
    previous = signal.signal(signal.SIGTERM, _interrupting_handler(os.getpid()))
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


_installed = False  # install_app_handlers ran in this process


def _exit_interrupted(err: BaseException, exit: Callable[[int], Any] = sys.exit) -> None:
    """Print ``cicfw: interrupted[ (SIGTERM)][; <what is kept>]`` and ``exit`` with 130 (Ctrl-C) or 128 + the
    signal."""
    detail = f"; {err}" if isinstance(err, Interrupted) and str(err) else ""
    by = f" ({signal.Signals(_stopped_by).name})" if _stopped_by else ""
    print(f"cicfw: interrupted{by}{detail}", file=sys.stderr)
    exit(128 + _stopped_by if _stopped_by else 130)


def install_app_handlers() -> None:
    """What an app started from the command line installs first thing, before importing the app itself
    (never an import): through the app's own imports and Hydra's composition too, SIGTERM stops it as
    Ctrl-C does, and an uncaught stop or ``CicfwError`` ends in the one line and status a later one would
    (130/143, 2) instead of a traceback or a silent exit. An empty ``CICFW_CACHE`` is dropped, so that
    ``${oc.env:CICFW_CACHE,<default>}`` means the default cache; a relative one is made absolute here, where
    the app starts, not in the run folder ``hydra.job.chdir=true`` moves into (a dataset collected per run);
    without ``HOME`` (and no cache given) the user's home from the password database stands in, as ``~`` does.
    Off the main thread or again: nothing."""
    global _installed
    cache = os.environ.get("CICFW_CACHE")
    if cache == "":
        del os.environ["CICFW_CACHE"]
    elif cache is not None and not os.path.isabs(os.path.expanduser(cache)):
        os.environ["CICFW_CACHE"] = os.path.abspath(cache)
    if "HOME" not in os.environ and cache is None:  # the configs' default cache is ${oc.env:HOME}/.cache/cicfw
        with suppress(KeyError, RuntimeError):  # no entry in the password database: Hydra names HOME
            os.environ["HOME"] = str(Path.home())  # what ~ means without HOME (a batch job's environment)
    if _installed or threading.current_thread() is not threading.main_thread() \
            or signal.getsignal(signal.SIGTERM) is None:
        return
    _installed = True
    guard_stdout()
    previous = sys.excepthook

    def uncaught(kind: type[BaseException], err: BaseException, tb: object) -> None:
        global _exit_status
        if issubclass(kind, CicfwError) and not debugging():
            print(f"cicfw: error: {err}", file=sys.stderr)
            _exit_now(2)
        if not issubclass(kind, KeyboardInterrupt):
            _exit_status = 1  # Python's status after a traceback, kept if stdout failed too (_report_stdout_failure)
            previous(kind, err, tb)
            return
        _exit_interrupted(err, _exit_now)

    sys.excepthook = uncaught
    # the handler last: a SIGTERM the moment it is in place must already find the hook that makes it one line
    signal.signal(signal.SIGTERM, _interrupting_handler(os.getpid()))


class GuardedStdout:
    """An app's ``sys.stdout``: the first write or flush that fails points the descriptor at the null device
    and drops what comes after, so the app goes on with its work and its files (the log file holds every
    line). A closed pipe (``app | head``) ends nothing: the app exits as it would have, quietly (Python's
    "Note on SIGPIPE"). Any other failure (a full disk) is ``failure``: one line at exit, status 2."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream
        self.closed_pipe = False
        self.failure: OSError | None = None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)

    def _lost(self, err: OSError) -> None:
        """Stop writing: the descriptor goes to the null device (Python's own flush at exit then succeeds)."""
        if err.errno == errno.EPIPE:
            self.closed_pipe = True
        else:
            self.failure = err
        with suppress(Exception):
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, self._stream.fileno())
            os.close(devnull)
        if log.hasHandlers():  # an app's log file: say there why the terminal's part stops (not on stderr)
            log.warning("stdout %s; the rest goes to the log file only", "was closed" if self.closed_pipe
                        else f"could not be written ({err.strerror or err})")

    @property
    def lost(self) -> bool:
        return self.closed_pipe or self.failure is not None

    def write(self, text: str) -> int:
        if not self.lost:
            try:
                return self._stream.write(text)
            except OSError as err:
                self._lost(err)
        return len(text)

    def flush(self) -> None:
        if not self.lost:
            try:
                self._stream.flush()
            except OSError as err:
                self._lost(err)


def guard_stdout() -> None:
    """Put ``GuardedStdout`` in place of ``sys.stdout`` and, at exit, flush it and turn a failed write into
    ``cicfw: error: could not write to stdout: <why>`` and status 2 (the status an app ended with
    otherwise, where it was not 0 and the handlers saw it: a user error's, an interruption's, a traceback's 1;
    a ``SystemExit(n)`` is not seen). Called by ``install_app_handlers``."""
    global _stdout_checked_at_exit
    if isinstance(sys.stdout, GuardedStdout) or sys.stdout is None:
        return
    sys.stdout = GuardedStdout(sys.stdout)
    if not _stdout_checked_at_exit:
        _stdout_checked_at_exit = True
        atexit.register(_report_stdout_failure)


_stdout_checked_at_exit = False  # guard_stdout registered _report_stdout_failure

#: the status ``_exit_now`` ends the process with, while its exit handlers run
_exit_status: int | None = None


def _report_stdout_failure() -> None:
    """At exit: a write to stdout that failed (other than a closed pipe) is one line on stderr and a
    non-zero status, however the app ended."""
    out = sys.stdout
    if not isinstance(out, GuardedStdout):
        return
    out.flush()
    if out.failure is None:
        return
    print(f"cicfw: error: could not write to stdout: {out.failure.strerror or out.failure}", file=sys.stderr)
    with suppress(Exception):
        sys.stderr.flush()
    logging.shutdown()  # the handlers registered before this one are skipped by os._exit: flush the log files
    os._exit(_exit_status or 2)


def _exit_now(status: int) -> None:
    """Exit with ``status`` from ``sys.excepthook`` (where ``sys.exit`` would only be reported as an error
    in the hook): the exit handlers run (log files are flushed), then the process ends."""
    global _exit_status
    _exit_status = status
    try:
        atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:
                pass
        os._exit(status)


def _message(err: BaseException) -> object:
    return err.args[0] if isinstance(err, (KeyError, FileNotFoundError)) and err.args else err


def report_user_errors(fn: F) -> F:
    """Exit with ``cicfw: error: <message>`` (status 2) on a user error, and with ``cicfw: interrupted ...``
    on Ctrl-C or SIGTERM (``sigterm_as_interrupt``; status 130, or 143 for SIGTERM).

    In a multirun every failure is logged to the job's log and re-raised, so Hydra marks the job
    FAILED: the sweep summary records it with its error and the other jobs go on (all jobs of a
    batch run; the Optuna sweeper marks the trial failed). A non-finite result (a diverged training)
    fails the job the same way instead of reaching the sweeper.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        multirun = _in_multirun()
        try:
            with sigterm_as_interrupt():
                result = fn(*args, **kwargs)
        except KeyboardInterrupt as err:
            if multirun:
                raise
            _exit_interrupted(err)
        except USER_ERRORS as err:
            if multirun:
                log.error("job failed: %s", _message(err))
                raise
            if debugging():
                traceback.print_exc()
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

