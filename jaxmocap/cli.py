"""The ``jaxmocap`` command.

Each sub-command is a module of :mod:`jaxmocap.commands` registered here: a module listed in
``SUBCOMMANDS`` exposes ``add_parser(subparsers)``, which adds its parser and sets
``func=run`` (``run(args) -> int``). Bad user input raises :class:`UsageError` (or one of the
library's file-format errors, all :class:`~jaxmocap.errors.InputError` subclasses): it is
printed as one line on stderr and the exit code is 2 — argparse's own errors (an option out of
range) too, as one line.

Ctrl-C (SIGINT) and SIGTERM end any command with one line and exit code 130 (128 + SIGINT, the
shell's convention), never a traceback: every writer is atomic (:mod:`jaxmocap.io.atomic`),
so an interrupted command leaves nothing half-written; ``track`` catches the interrupt in its
frame loop and writes the frames tracked so far as a result marked partial.
"""

from __future__ import annotations

import argparse
import atexit
import builtins
import contextlib
import gc
import importlib
import opcode
import os
import signal
import sys
import threading
import typing

from jaxmocap.errors import InputError, UsageError

SUBCOMMANDS = (
    "jaxmocap.commands.demo",
    "jaxmocap.commands.build_db",
    "jaxmocap.commands.learn",
    "jaxmocap.commands.synth",
    "jaxmocap.commands.calibrate",
    "jaxmocap.commands.colors",
    "jaxmocap.commands.track",
    "jaxmocap.commands.evaluate",
    "jaxmocap.commands.body",
    "jaxmocap.commands.synth_world",
    "jaxmocap.commands.experiment",
    "jaxmocap.commands.tune",
)


EXIT_INTERRUPTED = 130


class Terminated(KeyboardInterrupt):
    """SIGTERM, delivered as an interrupt so that it takes the Ctrl-C path."""


class ArgumentError(UsageError):
    """An argument argparse rejects (unknown option, a value out of its range)."""

    def __init__(self, prog: str, message: str):
        super().__init__(f"{message} (see {prog} --help)")
        self.prog = prog


class _Parser(argparse.ArgumentParser):
    """argparse whose usage errors are :class:`ArgumentError` (one line, exit code 2, returned
    by :func:`main`; the full usage is in ``--help``)."""

    def error(self, message: str):
        raise ArgumentError(self.prog, message)


def _in_finaliser(frame) -> bool:
    """Whether ``frame`` runs a garbage-collector callback or a ``__del__``: Python prints an
    exception raised there as "Exception ignored" (a traceback) and drops it."""
    codes = {getattr(cb, "__code__", None) for cb in gc.callbacks}
    for _ in range(8):
        if frame is None:
            return False
        if frame.f_code in codes or frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


def _importing(frame) -> bool:
    """Whether a module is being imported somewhere up the stack of ``frame``: importlib's
    frames, or :func:`_import`'s own (a signal landing there, before or after the import
    proper, may be in an import that native code called)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib") or \
                frame.f_code is _import.__code__:
            return True
        frame = frame.f_back
    return False


LOST_INTERRUPT_S = 15.0  # an interrupt no handler has reported by then ends the process
RESEND_S = 0.02  # a signal deferred outside an import statement (a finaliser) is sent again
_RAISED: list[int] = []  # the signals the handler raised as an interrupt in this run of main
_DEFERRED: list[int] = []  # a signal that arrived where it could not be raised, not yet raised
_RESENT: list[int] = []  # signals the re-send timer sent (each read once by the handler)
_TIMERS: list[threading.Timer] = []  # signals to send again, the lost-interrupt watchdog
_STATE = {"command": "jaxmocap", "reported": False}


def _timer(seconds: float, fn, *args) -> None:
    timer = threading.Timer(seconds, fn, args)
    timer.daemon = True
    _TIMERS.append(timer)
    timer.start()


def _report_interrupt(terminated: bool) -> None:
    """The one line of an interrupted command (main's, or the watchdog's)."""
    what = "terminated" if terminated else "interrupted"
    print(f"{_STATE['command']}: {what}; nothing written", file=sys.stderr, flush=True)


def _exit_if_lost(signum: int) -> None:
    """The interrupt raised ``LOST_INTERRUPT_S`` ago never reached a handler (a library caught
    it): report it as main would and end the process. Outputs are only renamed into place
    when complete, so what is left behind is at most a temporary, swept by the next run."""
    if _STATE["reported"]:
        return
    with contextlib.suppress(Exception):
        _report_interrupt(signum == signal.SIGTERM)
    os._exit(EXIT_INTERRUPTED)


def _raise_interrupt(signum: int):
    """Raise ``signum`` as the interrupt, recorded (:func:`interrupt_received`) and watched
    (the lost-interrupt watchdog)."""
    _DEFERRED.clear()
    if not _RAISED:
        _timer(LOST_INTERRUPT_S, _exit_if_lost, signum)
    _RAISED.append(signum)
    raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt


def _resend(signum: int) -> None:
    """The re-send timer: the deferred signal again, unless it has been raised meanwhile."""
    if _DEFERRED:
        _RESENT.append(signum)
        os.kill(os.getpid(), signum)


def _on_signal(signum, frame):
    """SIGINT/SIGTERM -> KeyboardInterrupt/Terminated, raised in our code or the libraries'
    ordinary code.

    Where an exception cannot travel it is not raised but deferred: while a module is
    imported (raised there it has been wrapped by ctypes into ``ctypes.ArgumentError`` in
    PyOpenGL's import, and leaving a string ``exec`` it makes CPython's exit re-raise SIGINT,
    see :func:`entry`) it is raised where the outermost ``import`` statement ends
    (:func:`_import`: at a fixed point, whatever the timing); in a finaliser (Python prints
    it as "Exception ignored" and drops it), or an import not made by an ``import`` statement
    (``importlib.import_module``, or native code: ``PyImport_Import`` from jaxlib's nanobind
    modules, see :func:`_import`), the signal is sent again ``RESEND_S`` later, and raised by
    the first copy that lands outside an import and a finaliser. The signal raised is
    recorded, so that an exception a library made of it still reads as the interrupt in
    :func:`main`, and a watchdog ends the process if no handler reports it within
    ``LOST_INTERRUPT_S`` (a library swallowed it)."""
    resent = bool(_RESENT)
    if resent:
        _RESENT.pop()
    if _in_finaliser(frame) or _importing(frame):
        if not _DEFERRED:
            _DEFERRED.append(signum)
        _timer(RESEND_S, _resend, signum)
        return
    if resent and not _DEFERRED:
        return  # the re-sent copy of an interrupt already raised where its import ended
    _raise_interrupt(signum)


_BUILTIN_IMPORT = builtins.__import__
_IMPORT_NAME = opcode.opmap["IMPORT_NAME"]


def _import_statement(frame) -> bool:
    """Whether ``frame`` is executing an ``import`` statement (its current instruction is
    ``IMPORT_NAME``), i.e. the ``__import__`` it called was called by Python code. Native code
    calls ``__import__`` too (``PyImport_Import``, e.g. nanobind's ``module_::import_``): the
    innermost Python frame is then the one that called into native code, which is executing
    a call, not ``IMPORT_NAME``."""
    return frame.f_code.co_code[frame.f_lasti] == _IMPORT_NAME


# unwrapped (the tests' jaxtyping import hook wraps every function not marked so): its own
# frame and its caller's, the frame that called __import__, are what the checks read
@typing.no_type_check
def _import(*args, **kwargs):
    """``__import__`` while :func:`main` runs: an interrupt deferred during the import is
    raised as soon as the outermost ``import`` statement of the main thread is done.

    Only an ``import`` statement's: an exception raised at the end of an import that native
    code started returns into that native code, and jaxlib's nanobind modules (which import
    ``jaxlib.mlir`` dialect modules while a program is lowered) turn it into a C++
    ``nanobind::python_error`` that can reach ``std::terminate`` (the process aborts, exit
    status -6, no line). Such an interrupt stays deferred until the import is over: a re-sent
    copy (:func:`_on_signal`) raises it in the Python code that runs next outside an import,
    or the next ``import`` statement raises it where it ends. (Python code that native code
    calls, and that runs an ``import`` statement, can still receive it there, as it can
    receive any interrupt that lands in it.)"""
    module = _BUILTIN_IMPORT(*args, **kwargs)
    if _DEFERRED and threading.current_thread() is threading.main_thread():
        caller = sys._getframe(1)
        if _import_statement(caller) and not (_importing(caller) or _in_finaliser(caller)):
            _raise_interrupt(_DEFERRED[0])
    return module


def acknowledge_interrupt() -> None:
    """Tell the lost-interrupt watchdog that a handler has taken the interrupt (and may take
    its time to write what it has)."""
    _STATE["reported"] = True


def interrupt_received() -> int | None:
    """The signal the handler last raised as an interrupt in this run of :func:`main`, or None:
    whatever exception follows it is the interrupt, however a library wrapped it."""
    return _RAISED[-1] if _RAISED else None


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="jaxmocap",
        description="Differentiable markerless motion capture: the colour-shirt tracker of "
        "Wang et al. 2011 and the stereo particle-filter tracker of Azad et al. 2007.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=_Parser)
    for name in SUBCOMMANDS:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    previous = {}
    del _RAISED[:], _TIMERS[:], _DEFERRED[:], _RESENT[:]
    _STATE.update(command="jaxmocap", reported=False)
    with contextlib.suppress(ValueError):  # only the main thread may set handlers
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, _on_signal)
    if previous:
        builtins.__import__ = _import
    try:
        from jaxmocap._config import choose_offscreen_gl, enable_side_device

        choose_offscreen_gl()  # before anything imports MuJoCo
        enable_side_device()  # before anything starts JAX's backend
        args = build_parser().parse_args(argv)
        _STATE["command"] = f"jaxmocap {args.command}"
        from jaxmocap._config import enable_compilation_cache

        enable_compilation_cache()
        return int(args.func(args) or 0)
    except BaseException as err:
        if isinstance(err, KeyboardInterrupt) or _RAISED:
            # an interrupt, possibly wrapped by the library it landed in (see _on_signal)
            acknowledge_interrupt()
            _report_interrupt(isinstance(err, Terminated) or signal.SIGTERM in _RAISED)
            return EXIT_INTERRUPTED
        if not isinstance(err, (InputError, OSError)):
            raise
        if isinstance(err, OSError):  # the path and the cause in words (disk full, ...)
            from jaxmocap.io.atomic import describe_os_error

            msg = describe_os_error(err)
        else:
            msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        prog = err.prog if isinstance(err, ArgumentError) else _STATE["command"]
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return 2
    finally:
        for timer in _TIMERS:  # a signal still to be sent again would meet the old handler
            timer.cancel()
        if builtins.__import__ is _import:
            builtins.__import__ = _BUILTIN_IMPORT
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def entry() -> None:
    """The ``jaxmocap`` console script and ``python -m jaxmocap.cli``: run :func:`main` and
    exit with its status.

    After an interrupt the process ends through ``os._exit`` once the atexit handlers have run
    and the standard streams are flushed. Run with ``python -m``, CPython's normal exit
    re-raises SIGINT (exit status -2, not 130) whenever a KeyboardInterrupt has left a string
    ``exec`` (``dataclasses`` and ``typing`` run them while modules are imported) and no later
    string ``exec`` cleared the mark, even though main handled the interrupt. (Imports are
    shielded from the interrupt, see :func:`_on_signal`; other string ``exec`` calls are not.)
    """
    code = main()
    if code == EXIT_INTERRUPTED:
        atexit._run_exitfuncs()
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(code)
    sys.exit(code)


if __name__ == "__main__":
    entry()
