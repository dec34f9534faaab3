"""Recorded pedestrian trajectories (ETH/BIWI and UCY) as data: the file formats, resampling onto the simulator's
time step, the padded arrays a compiled program takes, and the catalogue of the standard recordings with their
download (`tgrf-data fetch eth-ucy`). NumPy and the standard library only; nothing here knows the simulator.

    from tgrf_jax.pedestrians import load_file, pack

    scene = load_file("crowds_zara01.txt", seconds_per_frame=0.04, dt=0.25)
    scene.positions, scene.mask          # (T, P, 2) float32 metres, (T, P) bool
    scene.max_crowd()                    # Crowd(count, step, time)

docs/pedestrians.md describes the formats, the splits and the terms of use of the recordings.
"""

from tgrf_jax.pedestrians.catalogue import (
    DATASETS,
    ETH_UCY,
    FOLDS,
    Entry,
    default_data_dir,
    load_entries,
    split,
)
from tgrf_jax.pedestrians.recordings import (
    DEFAULT_DT,
    FORMATS,
    SPEED_RANGE,
    Crowd,
    PackedScenes,
    RecordingError,
    RecordingSpec,
    Scene,
    load,
    load_file,
    pack,
    read_annotations,
)

__all__ = [
    "DATASETS",
    "DEFAULT_DT",
    "ETH_UCY",
    "FOLDS",
    "FORMATS",
    "SPEED_RANGE",
    "Crowd",
    "Entry",
    "PackedScenes",
    "RecordingError",
    "RecordingSpec",
    "Scene",
    "default_data_dir",
    "load",
    "load_entries",
    "load_file",
    "pack",
    "read_annotations",
    "split",
]
