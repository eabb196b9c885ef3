"""The ``cellcal`` command (``cellcal.core.cli:main``): one thin module per subcommand.

This package and :func:`main` import nothing heavy: main's first step is to take over
Ctrl-C, and only then does it import the implementation (:mod:`cellcal.core.cli.app`:
the parser, every subcommand, numpy, scipy), so an interrupt at any moment ends with
one line and exit status 130 instead of a traceback (ADR 0008, "Interrupts").
"""

from __future__ import annotations

import atexit
import contextlib  # loaded at start-up already, like os and sys
import os
import signal
import sys
from typing import TYPE_CHECKING, Any

from cellcal.core.cli.exits import EXIT_FAILURE, EXIT_INTERRUPTED, EXIT_OK, EXIT_USAGE
from cellcal.core.console import say

if TYPE_CHECKING:
    from collections.abc import Sequence
    from types import FrameType

__all__ = ["EXIT_FAILURE", "EXIT_INTERRUPTED", "EXIT_OK", "EXIT_USAGE", "build_parser", "main"]


#: Ctrl-C presses put off while an import is under way (5 ms apart: 2 s), then delivered wherever they land.
MAX_DEFERRED = 400


def _say(text: str) -> None:
    """One line on stderr, on a line of its own, never raising (stderr may be closed or a broken pipe)."""
    with contextlib.suppress(Exception):
        say(text)


class _Interrupts:
    """The SIGINT handler of one :func:`main` call.

    The first Ctrl-C raises KeyboardInterrupt (the run stops its arm, finishes or discards
    its files and exits 130); further ones during that clean-up are noted but do not
    interrupt it, and the third quits at once. After main has decided its exit status,
    a Ctrl-C quits at once with 130 while the interpreter waits for threads to end; from
    its ``atexit`` callbacks on (the shutdown's last milliseconds, where Python resets
    SIGINT to its default and would die of the signal) it is ignored and the status stands.
    A first Ctrl-C that lands inside an import is put off until the import is done (C
    extensions that import, numpy's among them, may print a KeyboardInterrupt as a traceback).
    """

    def __init__(self) -> None:
        self.presses = 0
        self.deferred = 0
        self.finished = False
        self.previous_unraisable = sys.unraisablehook

    def __call__(self, signum: int, frame: FrameType | None) -> None:
        if self.presses == 0 and not self.finished and self.deferred < MAX_DEFERRED and _importing(frame):
            # raised inside importlib, a KeyboardInterrupt reaches C extensions that import (numpy, scipy) and
            # some print it as a traceback before turning it into an ImportError: deliver it once the import
            # is done (sent again every 5 ms while the frame is inside an import, for 2 s at most)
            self.deferred += 1
            _send_again_soon()
            return
        self.presses += 1
        if self.finished or self.presses >= 3:
            self.quit_now()
        if self.presses == 1:
            raise KeyboardInterrupt
        _say("cellcal: still stopping the devices and closing files; Ctrl-C once more to quit at once")

    def unraisable(self, info: Any) -> None:
        """``sys.unraisablehook``: a KeyboardInterrupt that a finaliser swallowed is delivered again.

        The first Ctrl-C may land in a ``__del__`` or a garbage-collector callback, where
        Python prints "Exception ignored" and goes on as if nothing happened; it is raised
        anew once the finaliser has returned: sent again from a thread 5 ms later (sent from
        here, or waited for here, Python would run the handler inside this hook, which
        ignores it again).
        """
        if isinstance(info.exc_value, KeyboardInterrupt) and self.presses == 1 and not self.finished:
            self.presses = 0
            _send_again_soon()
            return
        self.previous_unraisable(info)

    def quit_now(self) -> None:
        """Flush what was printed and end the process with status 130, skipping any clean-up."""
        _say("cellcal: interrupted")
        with contextlib.suppress(Exception):
            sys.stdout.flush()
        os._exit(EXIT_INTERRUPTED)


def _send_again_soon() -> None:
    """SIGINT to this process again 5 ms from now, from a thread (the handler runs once the main thread can)."""
    import _thread
    import time

    def send_again() -> None:
        time.sleep(0.005)
        os.kill(os.getpid(), signal.SIGINT)

    _thread.start_new_thread(send_again, ())


def _importing(frame: FrameType | None) -> bool:
    """Whether ``frame`` or a caller of it runs importlib's own code (an import under way)."""
    depth = 0
    while frame is not None and depth < 500:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame, depth = frame.f_back, depth + 1
    return False


def _install(handler: _Interrupts) -> Any:
    """Install ``handler`` for SIGINT; returns the previous handler, or None when it cannot be installed.

    Not installed outside the main thread (Python runs signal handlers there only) or
    when SIGINT is ignored (a background job), which stays so.
    """
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        return None
    try:
        return signal.signal(signal.SIGINT, handler)
    except ValueError:  # not the main thread
        return None


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``cellcal`` command; returns the exit status.

    Args:
        argv: The arguments after the program name; None reads ``sys.argv`` (the program
            itself). Called with None, the Ctrl-C handler stays in place after main returns
            (see :class:`_Interrupts` for the interpreter's shutdown); called with a list
            (in-process), the previous handler is restored.
    """
    handler = _Interrupts()
    previous = None
    try:
        previous = _install(handler)
        if previous is not None:
            sys.unraisablehook = handler.unraisable
        from cellcal.core.cli.app import run_command  # the heavy imports, under the handler

        code = run_command(argv)
    except KeyboardInterrupt:
        _say("cellcal: interrupted")
        code = EXIT_INTERRUPTED
    except BaseException:
        if not handler.presses:
            raise
        # an interrupt that a library turned into another error (numpy's import, for one, makes a
        # KeyboardInterrupt inside its C extension an ImportError)
        _say("cellcal: interrupted")
        code = EXIT_INTERRUPTED
    finally:
        handler.finished = True
        if previous is not None and argv is not None:
            signal.signal(signal.SIGINT, previous)
            sys.unraisablehook = handler.previous_unraisable
        elif previous is not None:
            atexit.register(_ignore_sigint)  # registered last, runs first: after the wait for threads
    return code


def _ignore_sigint() -> None:
    """From here on (the end of the interpreter's shutdown) Ctrl-C changes nothing."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def __getattr__(name: str) -> Any:
    """``build_parser`` is imported on first use (it pulls in every subcommand)."""
    if name == "build_parser":
        from cellcal.core.cli.app import build_parser

        return build_parser
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
