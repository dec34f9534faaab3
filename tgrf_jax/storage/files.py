"""Small result files written atomically: a reader (or a crash) sees the old content or the new, never half."""

from __future__ import annotations

import os
import pathlib


def write_atomic(path, text: str) -> None:
    path = pathlib.Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)
