"""Stopping training between chunks, with a checkpoint, when the process is asked to stop.

A chunk is one compiled program: a signal cannot cut it short, and without this module an interrupted run loses
every update since its last periodic checkpoint (up to `run.checkpoint_every` updates; minutes of work on a CPU).
Inside `stop_requests()`:

- SIGTERM (a scheduler, `kill`, `timeout`) and a first SIGINT (Ctrl-C, a notebook's interrupt) ask the training
  loop to stop after the chunk that is running: it saves a checkpoint of that update and raises
  KeyboardInterrupt, so `--resume` continues from there, bit-identically.
- A second SIGINT stops at once (KeyboardInterrupt where the process is), as Ctrl-C did before.
- A SIGINT that the process was started to ignore (a job started in the background of a non-interactive shell)
  stays ignored.

Handlers are installed only in the main thread (Python allows no other), and the previous ones come back on exit.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
from collections.abc import Iterator


class StopRequest:
    """Set by a signal handler; read by the training loop between chunks."""

    def __init__(self):
        self.signal_name: str | None = None

    def __bool__(self) -> bool:
        return self.signal_name is not None


@contextlib.contextmanager
def stop_requests(enabled: bool = True) -> Iterator[StopRequest]:
    request = StopRequest()
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield request
        return

    def handler(signum, frame):
        name = signal.Signals(signum).name
        if request and signum == signal.SIGINT:
            raise KeyboardInterrupt
        if not request:
            request.signal_name = name
            # os.write, not print: the handler may run while the main thread is inside a print; and a reader that
            # has gone (the parent that sent this signal) must not turn the stop into a crash
            try:
                os.write(
                    2,
                    f"\n{name}: stopping after the running chunk, with a checkpoint"
                    f"{' (Ctrl-C again: at once)' if signum == signal.SIGINT else ''}\n".encode(),
                )
            except OSError:
                pass

    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            previous[sig] = signal.signal(sig, handler)
    try:
        yield request
    finally:
        for sig, old in previous.items():
            signal.signal(sig, signal.SIG_DFL if old is None else old)  # None: a handler set outside Python
