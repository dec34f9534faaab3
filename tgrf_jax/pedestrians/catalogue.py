"""The known recordings (ETH/BIWI and UCY): where each is downloaded from, its SHA-256, its frame spacing and its
place in the leave-one-scene-out splits; and the user data directory they are kept in.

The recordings are never shipped with the package: `tgrf-data fetch eth-ucy` downloads them (docs/pedestrians.md).
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import pathlib
import sys

from tgrf_jax.pedestrians.recordings import DEFAULT_DT, RecordingError, RecordingSpec, Scene, load

DATA_ENV = "TGRF_JAX_DATA"  # overrides the platform's user data directory (files under $TGRF_JAX_DATA/pedestrians)

_OPENTRAJ = "https://raw.githubusercontent.com/crowdbotp/OpenTraj/97ec1d5e1b579f26febeaa9083705952deac338a"
_TRAJECTRON = (
    "https://raw.githubusercontent.com/StanfordASL/Trajectron-plus-plus/40dec06e9cfef9e0d5f5ec69da2c4058a556bba9"
    "/experiments/pedestrians/raw/raw/all_data"
)
_ETH_TERMS = (
    "ETH/BIWI: no licence is stated; cite S. Pellegrini, A. Ess, K. Schindler, L. van Gool, \"You'll never walk "
    'alone: modeling social behavior for multi-target tracking", ICCV 2009.'
)
_UCY_TERMS = (
    'UCY: free to use with credit; cite A. Lerner, Y. Chrysanthou, D. Lischinski, "Crowds by Example", '
    "Computer Graphics Forum (Eurographics) 2007."
)


@dataclasses.dataclass(frozen=True)
class Entry:
    """One recording file: `name` is its path inside the data directory; `fold` the leave-one-scene-out test
    scene it belongs to (None: always training data)."""

    name: str
    scene: str
    format: str
    seconds_per_frame: float
    url: str
    sha256: str
    fold: str | None
    terms: str

    def spec(self, data_dir: str | os.PathLike | None = None) -> RecordingSpec:
        path = pathlib.Path(data_dir or default_data_dir()) / self.name
        return RecordingSpec(path, self.seconds_per_frame, format=self.format)


def _ucy(file: str, scene: str, fold: str | None, sha256: str) -> Entry:
    # the UCY files of the ETH/UCY benchmark: 10 frames = 0.4 s
    return Entry(f"ucy/{file}", scene, "eth_ucy", 0.04, f"{_TRAJECTRON}/{file}", sha256, fold, _UCY_TERMS)


ETH_UCY: tuple[Entry, ...] = (
    Entry(
        "eth/obsmat.txt",
        "ETH (BIWI seq_eth)",
        "obsmat",
        0.4 / 6,  # frames 6 apart are 0.4 s
        f"{_OPENTRAJ}/datasets/ETH/seq_eth/obsmat.txt",
        "d452ae2185ecb1164c2fdf31e75f6236f4c2ffc02c751a6b2ae921740cbc60d1",
        "eth",
        _ETH_TERMS,
    ),
    Entry(
        "hotel/obsmat.txt",
        "Hotel (BIWI seq_hotel)",
        "obsmat",
        0.04,  # frames 10 apart are 0.4 s
        f"{_OPENTRAJ}/datasets/ETH/seq_hotel/obsmat.txt",
        "2b8577595204a6b780b80258fd50da35adb7293e3e06ad6f8e1b60965e7dde6e",
        "hotel",
        _ETH_TERMS,
    ),
    _ucy(
        "students001.txt", "UCY University", "univ", "a6d87f278d94136fe39b8be91555487a29ac77259ae403b9dba2d5c18caf7b5b"
    ),
    _ucy(
        "students003.txt", "UCY University", "univ", "e25798b660634330aa89f8bb259425de720e84d0873902726c1d1f4ccff21d6c"
    ),
    _ucy(
        "uni_examples.txt", "UCY University", None, "61f432c0ab3070ed0ef150fbeabcd7baf839cab5495a46e6105bd747f0a092a7"
    ),
    _ucy("crowds_zara01.txt", "UCY Zara", "zara1", "1147a1962a09abfb86f28c6cddcac862e095a0cf129b3016385b69eacdd09d85"),
    _ucy("crowds_zara02.txt", "UCY Zara", "zara2", "8a649d0f8c9ae75c87c4d23a85f892786b0aa30266e996c7be03e69dafff22ff"),
    _ucy("crowds_zara03.txt", "UCY Zara", None, "16b3e899932c4baacd07f45013d5b921f90bc5a29eb2b0fe42f4d7c904ac3108"),
)

# Download sets `tgrf-data fetch NAME` knows, looked up at call time (tests point them at a local server).
DATASETS: dict[str, tuple[Entry, ...]] = {"eth-ucy": ETH_UCY}
FOLDS = ("eth", "hotel", "univ", "zara1", "zara2")  # the standard leave-one-scene-out test scenes
TERMS = (_ETH_TERMS, _UCY_TERMS)


def default_data_dir() -> pathlib.Path:
    """Where recordings are kept: ``$TGRF_JAX_DATA/pedestrians``, else the platform's user data directory
    (``$XDG_DATA_HOME`` or ``~/.local/share`` on Linux, ``~/Library/Application Support`` on macOS,
    ``%LOCALAPPDATA%`` on Windows) + ``tgrf-jax/pedestrians``."""
    root = os.environ.get(DATA_ENV)
    if root:
        return pathlib.Path(root).expanduser() / "pedestrians"
    home = pathlib.Path.home()
    if sys.platform == "win32":
        base = pathlib.Path(os.environ.get("LOCALAPPDATA") or home / "AppData" / "Local")
    elif sys.platform == "darwin":
        base = home / "Library" / "Application Support"
    else:
        base = pathlib.Path(os.environ.get("XDG_DATA_HOME") or home / ".local" / "share")
    return base / "tgrf-jax" / "pedestrians"


def sha256_of(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def status(entry: Entry, data_dir: str | os.PathLike | None = None) -> str:
    """``verified``, ``missing`` or ``hash mismatch`` for `entry`'s file in `data_dir`."""
    path = pathlib.Path(data_dir or default_data_dir()) / entry.name
    if not path.is_file():
        return "missing"
    return "verified" if sha256_of(path) == entry.sha256 else "hash mismatch"


def split(fold: str, entries: tuple[Entry, ...] = ETH_UCY) -> tuple[tuple[Entry, ...], tuple[Entry, ...]]:
    """(training, test) entries of a leave-one-scene-out fold: the test scene's files, and every other file."""
    if fold not in FOLDS:
        raise RecordingError(f"unknown fold {fold!r}; the folds are {', '.join(FOLDS)}")
    return tuple(e for e in entries if e.fold != fold), tuple(e for e in entries if e.fold == fold)


def load_entries(
    entries: tuple[Entry, ...], data_dir: str | os.PathLike | None = None, dt: float = DEFAULT_DT
) -> list[Scene]:
    """Load catalogue files (each with its own frame spacing) onto a grid of step `dt`; a missing file is a
    RecordingError that says how to fetch it."""
    scenes = []
    for entry in entries:
        spec = entry.spec(data_dir)
        if not pathlib.Path(spec.path).is_file():
            raise RecordingError(f"{spec.path}: no such file; download the recordings with `tgrf-data fetch eth-ucy`")
        scenes.append(load(spec, dt=dt))
    return scenes
