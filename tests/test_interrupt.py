"""A long job's stop on a signal (gloam_jax.interrupt)."""

import signal
import time
import weakref

import pytest

from gloam_jax.interrupt import Terminated, raise_if_stopped, stop_on


class _Thing:
    pass


def _wait_for_the_signal() -> None:
    for _ in range(500):
        time.sleep(0.01)


def test_the_first_sigterm_raises_terminated_and_repeats_are_ignored():
    # What the process started with: a job started in the background inherits SIGINT ignored.
    before, before_int = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
    with pytest.raises(Terminated):
        with stop_on(signal.SIGTERM):
            signal.raise_signal(signal.SIGTERM)
            _wait_for_the_signal()
    assert signal.getsignal(signal.SIGTERM) is before
    with pytest.raises(KeyboardInterrupt) as caught:
        with stop_on(signal.SIGINT, signal.SIGTERM):
            signal.raise_signal(signal.SIGINT)
            _wait_for_the_signal()
    assert not isinstance(caught.value, Terminated)
    assert signal.getsignal(signal.SIGINT) is before_int


def test_an_interrupt_raised_inside_a_finaliser_is_delivered_again():
    def finaliser(_):
        signal.raise_signal(signal.SIGTERM)
        len([])  # a call: the handler runs here, inside the finaliser, where Python swallows it

    start = time.monotonic()
    with pytest.raises(Terminated):
        with stop_on(signal.SIGTERM):
            thing = _Thing()
            ref = weakref.ref(thing, finaliser)
            del thing
            assert ref() is None  # the finaliser has run, and the job carries on ...
            _wait_for_the_signal()  # ... until the interrupt arrives again
    assert time.monotonic() - start < 4.0


@pytest.mark.parametrize("check", [True, False])
def test_an_interrupt_that_code_swallowed_is_raised_at_the_next_check_or_the_end(check):
    """Extension code may clear an exception without a trace; the job then stops at its next
    raise_if_stopped (between trials or steps), else when the block ends."""
    reached = []
    with pytest.raises(Terminated):
        with stop_on(signal.SIGTERM):
            raise_if_stopped()  # nothing has come: carries on
            try:
                signal.raise_signal(signal.SIGTERM)
                _wait_for_the_signal()
            except KeyboardInterrupt:
                pass  # swallowed
            if check:
                raise_if_stopped()
            reached.append(True)
    assert reached == ([] if check else [True])
    raise_if_stopped()  # outside a block: nothing to raise
    with stop_on(signal.SIGTERM):
        raise_if_stopped()  # a new block starts clean


def test_stop_between_holds_the_first_signal_until_the_job_asks_and_not_the_second():
    from gloam_jax.interrupt import stop_between

    before = signal.getsignal(signal.SIGTERM)
    with stop_between(signal.SIGINT, signal.SIGTERM) as pending:
        assert pending() is None
        signal.raise_signal(signal.SIGTERM)
        time.sleep(0.01)  # the step in progress goes on
        assert pending() == signal.SIGTERM
        with pytest.raises(KeyboardInterrupt):  # a second signal stops it at once
            signal.raise_signal(signal.SIGINT)
            time.sleep(0.01)
    assert signal.getsignal(signal.SIGTERM) is before
