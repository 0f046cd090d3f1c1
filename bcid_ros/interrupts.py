"""
Ctrl-C that ends a run quietly, wherever it lands.

Python raises the KeyboardInterrupt of a SIGINT in whatever the main thread runs
next. When that is a finalizer (rclpy's ``Task.__del__`` while the collector
runs), Python prints "Exception ignored in ..." with a traceback and goes on as
if no signal had come. A node still stops, since rclpy's own signal handler has
shut its context down; a ``bcid`` command, whose contexts have no rclpy handler,
would not. :func:`handle_interrupts_in_finalizers` prints nothing in both cases
and, for the second, raises the interrupt again in the main thread.

While a node's modules load, before rclpy installs its handler, a library can
swallow the interrupt too: a C extension's import turns it into another
ImportError (numpy's "could not import module datetime"), or drops it and loads
on, and the node then spins with no signal left to stop it. So a node's console
script, and ``bcid``, defer SIGINT while they load (:func:`defer_sigints`): the
signal is only noted, and raised once loaded (:func:`interrupt_on_sigints`).
"""

from __future__ import annotations

import _thread
import signal
import sys
import threading
import time
from typing import Any

#: Seconds before an interrupt caught in a finalizer is raised again: enough for the
#: hook to return (microseconds), so that it lands after the finalizer.
REDELIVERY_DELAY = 0.01


def interrupted(error: BaseException | None) -> bool:
    """Return whether ``error`` is, or was caused by, a KeyboardInterrupt."""
    while error is not None:
        if isinstance(error, KeyboardInterrupt):
            return True
        error = error.__cause__ or error.__context__
    return False


_deliver_again = True
_previous_hook = sys.unraisablehook


def _on_unraisable(unraisable: Any) -> None:
    if not isinstance(unraisable.exc_value, KeyboardInterrupt):
        _previous_hook(unraisable)
    elif _deliver_again:
        # From another thread, a moment later: raised from here it would land inside
        # this hook and be ignored again (a threading.Thread's start() waits, too long).
        try:
            _thread.start_new_thread(_interrupt_main_later, ())
        except RuntimeError:    # no new thread while the interpreter shuts down
            pass


def _interrupt_main_later() -> None:
    time.sleep(REDELIVERY_DELAY)
    _thread.interrupt_main()    # does nothing if SIGINT is no longer Python's to handle


def handle_interrupts_in_finalizers(*, deliver_again: bool) -> None:
    """
    Print nothing for a KeyboardInterrupt raised inside a finalizer; raise it again if asked.

    Parameters
    ----------
    deliver_again : bool
        True where the interrupt is how the run learns of Ctrl-C (rclpy initialised
        without signal handlers). False in a node, where rclpy's handler shuts the
        context down: raised again, the interrupt could land in the node's own
        shutdown, while its state is being saved.

    """
    global _deliver_again, _previous_hook
    _deliver_again = deliver_again
    if sys.unraisablehook is not _on_unraisable:
        _previous_hook = sys.unraisablehook
        sys.unraisablehook = _on_unraisable


_sigint_noted = False


def _note(signum: int, frame: Any) -> None:
    global _sigint_noted
    _sigint_noted = True


def _note_and_interrupt(signum: int, frame: Any) -> None:
    _note(signum, frame)
    signal.default_int_handler(signum, frame)


def defer_sigints() -> None:
    """
    From now on a SIGINT is only noted: no KeyboardInterrupt, see :func:`sigint_noted`.

    Leaves SIGINT alone where it is neither Python's default nor ours (ignored, as in
    a background job, or someone else's handler), and off the main thread, where
    Python takes no handler (and delivers no SIGINT).
    """
    global _sigint_noted
    _sigint_noted = False
    if threading.current_thread() is not threading.main_thread():
        return
    previous = signal.signal(signal.SIGINT, _note)
    if previous not in (signal.default_int_handler, _note_and_interrupt):
        signal.signal(signal.SIGINT, previous)


def interrupt_on_sigints() -> None:
    """
    Undo :func:`defer_sigints`: a SIGINT raises KeyboardInterrupt again (and is noted).

    Raises KeyboardInterrupt at once if one was noted meanwhile: no moment is left
    where a SIGINT is neither raised nor about to be.
    """
    if (threading.current_thread() is threading.main_thread()
            and signal.getsignal(signal.SIGINT) is _note):
        signal.signal(signal.SIGINT, _note_and_interrupt)
    if _sigint_noted:
        raise KeyboardInterrupt


def sigint_noted() -> bool:
    """Return whether a SIGINT came since :func:`defer_sigints`."""
    return _sigint_noted
