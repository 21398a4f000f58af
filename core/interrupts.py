"""Ctrl-C in the command-line programs (``python -m training``, ``pipeline``, ``studies``): one line and
exit 130, however often it is pressed and wherever the presses land.

:func:`install` runs first in a program's ``__main__``, before its heavy imports (torch alone takes
seconds, and a press there printed a traceback): the first Ctrl-C raises KeyboardInterrupt, as Python's
own handler does, and from then on Ctrl-C is ignored (:func:`stopping`). The program is on its way out
and says so in one line; a second KeyboardInterrupt could only land in its clean-up (a ``finally``, a
DataLoader's or a pool's ``__del__``, an ``atexit`` callback) and print a traceback or "Exception ignored
in ..." after that line, or cut the clean-up short (a LocalCluster left to close at exit, a pool's
semaphores leaked). Ignoring, unlike a handler written in Python, also outlives the interpreter's
finalisation (a press there ended the process by SIGINT, exit -2, not 130). A command that does more
with Ctrl-C (``train`` finishes the step under way) installs its own handler for that while and calls
:func:`stopping` when it stops. A first press whose handler runs where Python would swallow its
KeyboardInterrupt (a garbage collector's callback, a ``__del__``) is delivered again just after.

:func:`held_back` starts processes with Ctrl-C held back, so that they begin with SIGINT blocked: a press
that reached a child before its own set-up ignored SIGINT printed the child's traceback.
"""
from __future__ import annotations

import contextlib
import signal
import threading


def install() -> None:
    """The first Ctrl-C raises KeyboardInterrupt; every later one is ignored (:func:`stopping`). A process
    started with Ctrl-C ignored (a shell's background job) keeps ignoring it, as Python does."""
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signal.signal(signal.SIGINT, _first_press)


def _first_press(signum, frame) -> None:
    if _swallowed(frame):
        # Python prints "Exception ignored in ..." for an exception raised here and goes on: the press would
        # be lost (a dataset run pressed five times ran to its end). Deliver it again once this is over.
        _redeliver(signum)
        return
    stopping()
    raise KeyboardInterrupt


def _swallowed(frame) -> bool:
    """Whether an exception raised at ``frame`` would be swallowed: it runs inside a garbage collector's
    callback (``gc.callbacks``: distributed registers one) or a ``__del__``."""
    import gc
    codes = {getattr(getattr(cb, "__func__", cb), "__code__", None) for cb in list(gc.callbacks)}
    while frame is not None:
        if frame.f_code in codes or frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


def _redeliver(signum: int, delay: float = 0.02) -> None:
    """The press again in ``delay`` seconds, from a thread (the handler then runs outside what swallowed it)."""
    import os
    t = threading.Timer(delay, os.kill, (os.getpid(), signum))
    t.daemon = True
    t.start()


def stopping() -> None:
    """From now on Ctrl-C does nothing in this process: it is stopping (or done) and says so once.
    In the main thread only (elsewhere: nothing)."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)


@contextlib.contextmanager
def held_back():
    """SIGINT blocked in this thread meanwhile: processes (and threads) started here begin with it blocked.
    A press meanwhile takes effect when the block ends, not in the middle: a KeyboardInterrupt raised
    while a pool's worker was being spawned left that worker waiting on its parent's pipe, and it printed
    an ``EOFError`` traceback after the command's one line. (Blocking alone does not defer it: another
    thread takes the signal, and Python runs the handler in this one at once.) Multiprocessing's resource
    tracker is started first: starting it unblocks SIGINT in the calling thread
    (``resource_tracker.ensure_running``), and a pool's first lock starts it before the workers."""
    from multiprocessing import resource_tracker
    resource_tracker.ensure_running()
    main = threading.current_thread() is threading.main_thread()
    before = signal.getsignal(signal.SIGINT) if main else None
    defer = main and before not in (signal.SIG_IGN, signal.SIG_DFL, None)
    pressed = []
    if defer:
        signal.signal(signal.SIGINT, lambda signum, frame: pressed.append(signum))
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)     # a press still pending arrives here
        if defer:
            signal.signal(signal.SIGINT, before)
    if pressed:
        if before is _first_press:
            stopping()
        raise KeyboardInterrupt
