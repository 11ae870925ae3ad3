"""How a long job stops on a signal: the first Ctrl-C or SIGTERM raises KeyboardInterrupt
(SIGTERM as :class:`Terminated`) through the job's own clean-up, which marks the running trial
failed or checkpoints the last step; repeats are ignored so that the clean-up completes.

Python runs a signal's handler at the next bytecode of the main thread, which may belong to a
finaliser (a weakref callback, ``__del__``). An exception raised there is reported as
"ignored" and the job carries on, its repeats now ignored: the job would run to its end. So an
interrupt swallowed that way is sent again, from another thread, once the finaliser is done.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator


class Terminated(KeyboardInterrupt):
    """SIGTERM, taking the same way out as Ctrl-C."""


def _raise_once(signum: int, frame: object) -> None:
    for repeat in (signal.SIGINT, signal.SIGTERM):
        signal.signal(repeat, signal.SIG_IGN)
    raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt


@contextlib.contextmanager
def stop_on(*signums: int) -> Iterator[None]:
    """Within the block, the first of ``signums`` (SIGINT, SIGTERM) raises KeyboardInterrupt
    or :class:`Terminated` and ignores both from then on; an interrupt raised inside a
    finaliser is delivered again. Handlers and ``sys.unraisablehook`` are restored after."""
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
    try:
        yield
    finally:
        sys.unraisablehook = hook
        for s, handler in previous.items():
            signal.signal(s, handler)
