"""tgrf_jax.train.stop: which signals ask for a stop between chunks, which stop at once, and what is left alone
(the training loop's side, a checkpoint and a bit-identical resume: tests/test_train_cli.py)."""

import signal
import threading

import pytest
from helpers import signal_this_thread

from tgrf_jax.train.stop import stop_requests


def _send(sig):
    signal_this_thread(sig)


@pytest.fixture
def ctrl_c_enabled():
    """SIGINT as an interactive Python process has it: a suite started in the background of a non-interactive
    shell inherits an ignored SIGINT, which stop_requests rightly leaves ignored."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, previous)


def test_first_ctrl_c_is_a_request_and_the_second_stops_at_once(capfd, ctrl_c_enabled):
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt):
        with stop_requests() as stop:
            assert not stop
            _send(signal.SIGINT)
            assert stop and stop.signal_name == "SIGINT"
            _send(signal.SIGTERM)  # another request: changes nothing
            assert stop.signal_name == "SIGINT"
            _send(signal.SIGINT)
            pytest.fail("a second Ctrl-C must interrupt at once")
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    assert "SIGINT: stopping after the running chunk, with a checkpoint" in capfd.readouterr().err


def test_sigterm_is_a_request_every_time():
    with stop_requests() as stop:
        for _ in range(3):
            _send(signal.SIGTERM)
        assert stop.signal_name == "SIGTERM"


def test_an_ignored_sigint_stays_ignored():
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)  # as in a job started with & by a script
    try:
        with stop_requests() as stop:
            _send(signal.SIGINT)
            assert not stop and signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, previous)


def test_disabled_or_off_the_main_thread_nothing_is_installed():
    before = signal.getsignal(signal.SIGTERM)
    with stop_requests(enabled=False):
        assert signal.getsignal(signal.SIGTERM) is before
    seen = []

    def in_a_thread():
        with stop_requests() as stop:
            seen.append((bool(stop), signal.getsignal(signal.SIGTERM) is before))

    worker = threading.Thread(target=in_a_thread)
    worker.start()
    worker.join()
    assert seen == [(False, True)]
