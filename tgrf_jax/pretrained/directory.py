"""A policy directory as one unit.

`manifest.json` lists the SHA-256 of every other file of the directory and is written last; `verify` refuses a
directory whose files do not match it (a file changed, damaged, missing or added), naming the file. `writing`
builds a directory in a hidden sibling (`.NAME.*.tgrf-partial`) renamed into place once the manifest is written,
so a reader sees the whole directory or none of it. The writer holds an OS lock on its temporary directory while
it works; the next writer into the same parent removes every such directory whose lock is free, which is what an
interrupted (killed) writer leaves behind.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import pathlib
import re
import shutil
import tempfile
from collections.abc import Iterable, Iterator

from tgrf_jax.config import ConfigError

MANIFEST_FILE = "manifest.json"
MANIFEST_FORMAT = "tgrf-jax policy directory"
MANIFEST_VERSION = 1
PARTIAL_SUFFIX = ".tgrf-partial"
_HEX64 = re.compile(r"[0-9a-f]{64}")


def file_sha256(path: pathlib.Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def write_manifest(directory: str | pathlib.Path) -> pathlib.Path:
    """Write `directory/manifest.json` with the SHA-256 of every other file in it (a policy directory holds only
    files). Writers call it last; call it yourself only on a directory whose files you trust."""
    directory = pathlib.Path(directory)
    entries = sorted(p for p in directory.iterdir() if p.name != MANIFEST_FILE)
    odd = [p for p in entries if p.is_symlink() or not p.is_file()]
    if odd:
        raise ConfigError(f"{str(odd[0])!r}: a policy directory holds only plain files")
    manifest = {
        "format": MANIFEST_FORMAT,
        "version": MANIFEST_VERSION,
        "sha256": {p.name: file_sha256(p) for p in entries},
    }
    path = directory / MANIFEST_FILE
    path.write_text(json.dumps(manifest, indent=2) + "\n")
    return path


def _read_manifest(directory: pathlib.Path) -> dict[str, str]:
    path = directory / MANIFEST_FILE
    if not path.is_file():
        raise ConfigError(
            f"{str(path)!r} missing: a policy directory lists the SHA-256 of its files there (tgrf-export and "
            "tgrf_jax.pretrained.export write it); write the directory again, or, for files you trust, "
            "call tgrf_jax.pretrained.write_manifest(DIR)"
        )
    try:
        manifest = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, ValueError) as e:
        raise ConfigError(f"{str(path)!r}: cannot read the manifest ({type(e).__name__}: {e})") from None
    digests = manifest.get("sha256") if isinstance(manifest, dict) else None
    if (
        not isinstance(digests, dict)
        or manifest.get("format") != MANIFEST_FORMAT
        or manifest.get("version") != MANIFEST_VERSION
    ):
        raise ConfigError(
            f"{str(path)!r} is not a version-{MANIFEST_VERSION} {MANIFEST_FORMAT!r} manifest "
            "(keys 'format', 'version', 'sha256')"
        )
    for name, digest in digests.items():
        if pathlib.PurePath(name).name != name or name in ("", ".", "..", MANIFEST_FILE):
            raise ConfigError(f"{str(path)!r} lists {name!r}, which is no file name of this directory")
        if not isinstance(digest, str) or not _HEX64.fullmatch(digest):
            raise ConfigError(f"{str(path)!r}: the SHA-256 of {name!r} is {digest!r}, not 64 lowercase hex digits")
    return digests


def verify(directory: str | pathlib.Path, required: Iterable[str] = ()) -> None:
    """Refuse `directory` unless its files are exactly those of its manifest, each with its listed SHA-256, and
    the manifest lists every name in `required`. Raises ConfigError naming the first offending file."""
    directory = pathlib.Path(directory)
    digests = _read_manifest(directory)
    for name in required:
        if name not in digests:
            raise ConfigError(f"{str(directory / name)!r} is not listed in {MANIFEST_FILE}")
    present = sorted(p.name for p in directory.iterdir() if p.name != MANIFEST_FILE)
    unlisted = [name for name in present if name not in digests]
    if unlisted:
        raise ConfigError(
            f"{str(directory / unlisted[0])!r} is not listed in {MANIFEST_FILE}: a policy directory holds only "
            "the files it was written with"
        )
    for name, digest in sorted(digests.items()):
        path = directory / name
        if path.is_symlink() or not path.is_file():
            raise ConfigError(f"{str(path)!r} is listed in {MANIFEST_FILE} but is missing (or not a plain file)")
        try:
            actual = file_sha256(path)
        except OSError as e:
            raise ConfigError(f"{str(path)!r}: cannot read it ({type(e).__name__}: {e})") from None
        if actual != digest:
            raise ConfigError(
                f"{str(path)!r} does not match {MANIFEST_FILE} (SHA-256 {actual[:12]}..., listed {digest[:12]}...): "
                "it was changed or damaged after the directory was written; write the policy again"
            )


def _lock(directory: pathlib.Path, *, wait: bool) -> int | None:
    """An open descriptor of `directory` holding its exclusive lock, or None when another process holds it."""
    fd = os.open(directory, os.O_RDONLY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
    except BlockingIOError:
        os.close(fd)
        return None
    return fd


def remove_stale(parent: pathlib.Path) -> list[pathlib.Path]:
    """Remove the temporary directories of interrupted writers in `parent` (those whose lock is free)."""
    removed = []
    for path in sorted(parent.glob(f".*{PARTIAL_SUFFIX}")):
        if path.is_symlink() or not path.is_dir():
            continue
        try:
            fd = _lock(path, wait=False)
        except OSError:  # vanished meanwhile (its writer finished) or unreadable: not ours to judge
            continue
        if fd is None:  # a writer is working in it
            continue
        try:
            shutil.rmtree(path)
            removed.append(path)
        except OSError:
            pass  # left for a later writer; it never blocks this one
        finally:
            os.close(fd)
    return removed


@contextlib.contextmanager
def writing(dest: str | pathlib.Path, *, replace: bool) -> Iterator[pathlib.Path]:
    """Yield a new empty temporary directory beside `dest`; on a clean exit write its manifest and rename it to
    `dest` (replacing an existing `dest` only with `replace`). On an error nothing is left behind."""
    dest = pathlib.Path(dest)
    dest.parent.mkdir(parents=True, exist_ok=True)
    remove_stale(dest.parent)
    tmp = pathlib.Path(tempfile.mkdtemp(prefix=f".{dest.name}.", suffix=PARTIAL_SUFFIX, dir=dest.parent))
    fd = _lock(tmp, wait=True)
    try:
        tmp.chmod(0o755)  # mkdtemp makes it private; a policy directory is for every user of the machine
        yield tmp
        write_manifest(tmp)
        if dest.exists() or dest.is_symlink():
            if not replace:
                raise ConfigError(f"{str(dest)!r} appeared while it was being written; the new files are discarded")
            if dest.is_symlink() or not dest.is_dir():
                dest.unlink()
            else:
                shutil.rmtree(dest)
        os.rename(tmp, dest)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp)
        os.close(fd)
