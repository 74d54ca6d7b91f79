"""fwdstep.core.signals: the first handled signal ends a command, later ones are ignored.

CI once printed the interruption twice: a second Ctrl-C arrived while the first was being
reported and raised again.  These tests deliver the signals in-process, at chosen moments,
so the property does not depend on timing."""
import os
import signal

import pytest

from fwdstep.core import signals


def test_a_second_signal_after_the_first_is_ignored():
    with signals.handled():
        with pytest.raises(signals.Interrupted) as info:
            os.kill(os.getpid(), signal.SIGINT)
        assert info.value.signum == signal.SIGINT
        os.kill(os.getpid(), signal.SIGINT)        # would raise again without the latch
        os.kill(os.getpid(), signal.SIGTERM)
        assert signals.pending() is None


def test_a_signal_while_deferred_is_reported_once_and_then_the_rest_ignored():
    with signals.handled():
        with signals.deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            os.kill(os.getpid(), signal.SIGINT)    # the first one counts
        late = signals.pending()
        assert late is not None and late.signum == signal.SIGTERM
        os.kill(os.getpid(), signal.SIGINT)        # after it was acted on: ignored
        assert signals.pending() is None


def test_each_command_starts_afresh():
    with signals.handled():
        with pytest.raises(signals.Interrupted):
            os.kill(os.getpid(), signal.SIGHUP)
    with signals.handled():                        # a new command: the latch is reset
        with pytest.raises(signals.Interrupted) as info:
            os.kill(os.getpid(), signal.SIGINT)
        assert info.value.signum == signal.SIGINT


def test_held_raises_a_signal_at_its_end_with_fwdsteps_handlers():
    with signals.handled():
        done = []
        with pytest.raises(signals.Interrupted) as info:
            with signals.held():
                os.kill(os.getpid(), signal.SIGTERM)
                done.append("the rest of the block ran")
        assert done and info.value.signum == signal.SIGTERM


@pytest.mark.parametrize("before", [signal.default_int_handler, signal.SIG_IGN])
def test_held_acts_at_its_end_as_the_handler_it_replaced(before):
    """The Python API: Python's own SIGINT handler would raise inside the block; an
    ignored SIGINT stays ignored."""
    previous = signal.signal(signal.SIGINT, before)
    try:
        done = []
        if before is signal.SIG_IGN:
            with signals.held():
                os.kill(os.getpid(), signal.SIGINT)
                done.append("the rest of the block ran")
        else:
            with pytest.raises(KeyboardInterrupt):
                with signals.held():
                    os.kill(os.getpid(), signal.SIGINT)
                    done.append("the rest of the block ran")
        assert done
        assert signal.getsignal(signal.SIGINT) == before
    finally:
        signal.signal(signal.SIGINT, previous)
