"""Download catalogue files over HTTP(S) (the standard library's urllib), each checked against its SHA-256 and
written atomically: the bytes go to a temporary file beside the destination, renamed into place only once the hash
matches, so a failed or interrupted download leaves nothing behind."""

from __future__ import annotations

import contextlib
import hashlib
import os
import pathlib
import tempfile
import urllib.error
import urllib.request
from collections.abc import Callable, Sequence
from typing import NamedTuple

from tgrf_jax.pedestrians.catalogue import Entry, sha256_of

TIMEOUT_S = 60.0
_CHUNK = 1 << 16


class FetchError(Exception):
    """A download that failed; the message starts with the URL."""

    def __init__(self, url: str, reason: str):
        super().__init__(f"{url}: {reason}")
        self.url = url
        self.reason = reason


class Outcome(NamedTuple):
    entry: Entry
    action: str  # "skipped" (already present and verified), "downloaded" or "failed"
    error: FetchError | None = None


def _download(url: str, dest: pathlib.Path, sha256: str, timeout: float) -> int:
    """Stream `url` to a temporary file in dest's directory, check its SHA-256, rename it to `dest`; returns the
    number of bytes. Raises FetchError; the temporary file is removed on any failure."""
    fd, tmp = tempfile.mkstemp(dir=dest.parent, prefix=f".{dest.name}.", suffix=".part")
    try:
        digest, size = hashlib.sha256(), 0
        with os.fdopen(fd, "wb") as out:
            try:
                request = urllib.request.Request(url, headers={"User-Agent": "tgrf-jax"})
                with urllib.request.urlopen(request, timeout=timeout) as response:
                    for block in iter(lambda: response.read(_CHUNK), b""):
                        digest.update(block)
                        out.write(block)
                        size += len(block)
            except urllib.error.HTTPError as e:
                raise FetchError(url, f"HTTP {e.code} {e.reason}") from None
            except urllib.error.URLError as e:
                raise FetchError(url, f"cannot connect ({e.reason})") from None
            except (OSError, ValueError) as e:  # timeouts, resets; ValueError: a malformed URL
                raise FetchError(url, f"download failed ({e})") from None
            out.flush()
            os.fsync(out.fileno())
        got = digest.hexdigest()
        if got != sha256:
            raise FetchError(url, f"SHA-256 {got} of the {size} bytes received differs from the expected {sha256}")
        os.replace(tmp, dest)
        return size
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def fetch(
    entries: Sequence[Entry],
    data_dir: str | os.PathLike,
    *,
    progress: Callable[[str], None] = print,
    timeout: float = TIMEOUT_S,
) -> list[Outcome]:
    """Bring every entry's file into `data_dir`: a file already present whose SHA-256 matches is kept, any other is
    downloaded. Every entry is tried; failures are returned (and reported through `progress`), not raised."""
    data_dir = pathlib.Path(data_dir)
    outcomes = []
    for entry in entries:
        dest = data_dir / entry.name
        if dest.is_file() and sha256_of(dest) == entry.sha256:
            progress(f"  {entry.name}: present, SHA-256 verified; skipped")
            outcomes.append(Outcome(entry, "skipped"))
            continue
        again = " (the file there has another SHA-256: replacing it)" if dest.exists() else ""
        progress(f"  {entry.name}: downloading {entry.url}{again}")
        created = [p for p in (dest.parent, *dest.parent.parents) if not p.exists()]
        try:
            dest.parent.mkdir(parents=True, exist_ok=True)
            size = _download(entry.url, dest, entry.sha256, timeout)
        except FetchError as e:
            for d in created:  # deepest first: leave no empty folder behind either
                with contextlib.suppress(OSError):
                    d.rmdir()
            progress(f"  {entry.name}: FAILED: {e}")
            outcomes.append(Outcome(entry, "failed", e))
            continue
        progress(f"  {entry.name}: {size / 1e6:.2f} MB, SHA-256 verified")
        outcomes.append(Outcome(entry, "downloaded"))
    return outcomes
