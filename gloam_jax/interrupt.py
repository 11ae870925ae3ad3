"""How a long job stops on a signal: the first Ctrl-C or SIGTERM raises KeyboardInterrupt
(SIGTERM as :class:`Terminated`) through the job's own clean-up, which marks the running trial
failed or checkpoints the last step; repeats are ignored so that the clean-up completes.

Python runs a signal's handler at the next bytecode of the main thread, which may belong to a
finaliser (a weakref callback, ``__del__``). An exception raised there is reported as
"ignored" and the job carries on, its repeats now ignored: the job would run to its end. So an
interrupt swallowed that way is sent again, from another thread, once the finaliser is done.
Extension code can also clear the exception without a trace; so the job calls
:func:`raise_if_stopped` where it passes only while running normally (between trials, between
steps), and a block that ends without the interrupt raises it on the way out.

A job whose state is whole only between its steps (an odometry run between frames) holds the
signal instead, with :func:`stop_between`: the step in progress completes, the job saves and
stops; a second signal stops it at once.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator


class Terminated(KeyboardInterrupt):
    """SIGTERM, taking the same way out as Ctrl-C."""


# The signals whose interrupt was raised inside the current stop_on block.
_raised: list[int] = []


def interrupt_for(signum: int) -> KeyboardInterrupt:
    """The exception of a stop for ``signum``: :class:`Terminated` (SIGTERM) or
    KeyboardInterrupt."""
    return Terminated() if signum == signal.SIGTERM else KeyboardInterrupt()


def _raise_once(signum: int, frame: object) -> None:
    for repeat in (signal.SIGINT, signal.SIGTERM):
        signal.signal(repeat, signal.SIG_IGN)
    _raised.append(signum)
    raise interrupt_for(signum)


def raise_if_stopped() -> None:
    """Raise the interrupt of a signal that came inside the block and whose exception something
    swallowed. Call it only where the job passes while running normally."""
    if _raised:
        for repeat in (signal.SIGINT, signal.SIGTERM):  # a redelivery on its way included
            signal.signal(repeat, signal.SIG_IGN)
        raise interrupt_for(_raised[0])


@contextlib.contextmanager
def stop_on(*signums: int) -> Iterator[None]:
    """Within the block, the first of ``signums`` (SIGINT, SIGTERM) raises KeyboardInterrupt
    or :class:`Terminated` and ignores both from then on; an interrupt raised inside a
    finaliser is delivered again, one swallowed elsewhere is raised at the next
    :func:`raise_if_stopped` or at the block's end. Handlers and ``sys.unraisablehook`` are
    restored after."""
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    for s in signums:
        signal.signal(s, _raise_once)
    hook = sys.unraisablehook

    def redeliver(unraisable: sys.UnraisableHookArgs) -> None:
        stop = unraisable.exc_value
        if not isinstance(stop, KeyboardInterrupt):
            hook(unraisable)
            return
        signum = signal.SIGTERM if isinstance(stop, Terminated) else signal.SIGINT
        for s in signums:
            signal.signal(s, _raise_once)
        # Not from here: the handler would run inside this hook, where it is swallowed again.
        again = threading.Timer(0.01, os.kill, (os.getpid(), signum))
        again.daemon = True
        again.start()

    sys.unraisablehook = redeliver
    _raised.clear()
    try:
        yield
        raise_if_stopped()
    finally:
        _raised.clear()
        sys.unraisablehook = hook
        for s, handler in previous.items():
            signal.signal(s, handler)


@contextlib.contextmanager
def stop_between(*signums: int) -> Iterator[Callable[[], int | None]]:
    """Within the block, the first of ``signums`` is only noted: the yielded ``pending()``
    returns it (else None), for the job to save and stop where its state is whole. A second
    signal raises KeyboardInterrupt or :class:`Terminated` at once. Outside the main thread,
    where Python sets no handlers, nothing is caught. Handlers are restored after."""
    if threading.current_thread() is not threading.main_thread():
        yield lambda: None
        return
    previous = {s: signal.getsignal(s) for s in signums}
    noted: list[int] = []

    def note(signum: int, frame: object) -> None:
        if noted:
            raise interrupt_for(signum)
        noted.append(signum)

    for s in signums:
        signal.signal(s, note)
    try:
        yield lambda: noted[0] if noted else None
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
