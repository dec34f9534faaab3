"""One writer per run or sweep directory: an exclusive lock held for the life of the process that writes it.

A second tgrf-train / tgrf-sweep / tgrf-reproduce on a directory that another process is writing (a `--resume`
started while the run still goes, say) stops with an error naming the directory and the holder's pid, instead
of both appending to the same files. The lock is an OS file lock, so it is released when its process dies,
however it dies.
"""

from __future__ import annotations

import contextlib
import os
import pathlib

import filelock

from tgrf_jax.fields import ConfigError

LOCK_FILE = ".lock"
OWNER_FILE = ".lock.owner"


@contextlib.contextmanager
def exclusive(directory, *, create: bool = True):
    directory = pathlib.Path(directory)
    if create:
        directory.mkdir(parents=True, exist_ok=True)
    elif not directory.is_dir():
        raise ConfigError(f"{str(directory)!r} does not exist")
    lock = filelock.FileLock(str(directory / LOCK_FILE), timeout=0)
    try:
        lock.acquire()
    except filelock.Timeout:
        try:
            holder = (directory / OWNER_FILE).read_text().strip() or "unknown"
        except OSError:
            holder = "unknown"
        raise ConfigError(
            f"{str(directory)!r} is being written by another process (pid {holder}); wait for it "
            "to finish or stop it first"
        ) from None
    try:
        (directory / OWNER_FILE).write_text(f"{os.getpid()}\n")
        yield directory
    finally:
        lock.release()
