"""Recorded pedestrian trajectories read from the ETH/UCY text formats and resampled onto the simulator's time grid.

Two layouts are read (the format is told by the number of columns, or stated):

- ``eth_ucy``: 4 columns ``frame id x y`` (metres), whitespace or tab separated: the ETH/UCY files of the
  trajectory-prediction literature (Social GAN, Trajectron++, Social-STGCNN).
- ``obsmat``: 8 columns ``frame id x z y vx vz vy`` (metres, m/s; z unused), the ETH/BIWI ``obsmat.txt`` files.
  The velocity columns are read only to explain a speed error; positions alone are resampled.

Neither layout states how many seconds one frame unit lasts, so every file comes with its `seconds_per_frame` (or
`fps`) from the caller. A wrong spacing scales every speed, which the median-walking-speed check below catches
when the error is large (a factor outside `SPEED_RANGE`).

Everything here is NumPy; a `Scene` and a `PackedScenes` hold plain arrays that a compiled program can take.
"""

from __future__ import annotations

import dataclasses
import math
import os
import pathlib
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

FORMATS = {"eth_ucy": 4, "obsmat": 8}  # format name -> number of columns
DEFAULT_DT = 0.25  # the simulator's default env.dt (seconds per step)
GAP_FACTOR = 1.5  # a person missing for more than this many usual steps has a gap: the track is split there
SPEED_RANGE = (0.3, 2.5)  # m/s: a median walking speed outside this range means wrong units or frame spacing
TYPICAL_SPEED = 1.3  # m/s: the speed a suggested frame spacing aims for
# Frame rates a suggested spacing is drawn from (besides "one annotation every 0.4 s", the ETH/UCY rate).
COMMON_FPS = (2.5, 5.0, 10.0, 12.5, 15.0, 24.0, 25.0, 30.0, 50.0, 60.0)
ANNOTATION_STEP_S = 0.4
# obsmat: the largest relative difference allowed between the median speed from positions and from the velocity
# columns (they agree within 1% on the ETH and Hotel recordings; a wrong spacing is off by its own factor)
VELOCITY_TOLERANCE = 0.25


class RecordingError(ValueError):
    """A recording that cannot be read or does not make sense; the message starts with the file (and line)."""


@dataclasses.dataclass(frozen=True)
class RecordingSpec:
    """A recording file and what the file does not say itself: the seconds per frame unit (give exactly one of
    `seconds_per_frame` and `fps`) and, optionally, its format (``eth_ucy`` or ``obsmat``; default: told by the
    number of columns)."""

    path: str | os.PathLike
    seconds_per_frame: float | None = None
    fps: float | None = None
    format: str | None = None

    def __post_init__(self) -> None:
        if (self.seconds_per_frame is None) == (self.fps is None):
            raise RecordingError(f"{self.path}: give exactly one of seconds_per_frame and fps")
        value = self.seconds_per_frame if self.fps is None else self.fps
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            name = "seconds_per_frame" if self.fps is None else "fps"
            raise RecordingError(f"{self.path}: {name} must be a positive number, got {value!r}")
        if self.format is not None and self.format not in FORMATS:
            raise RecordingError(f"{self.path}: unknown format {self.format!r}; allowed: {_allowed_formats()}")

    @property
    def frame_seconds(self) -> float:
        return float(self.seconds_per_frame) if self.fps is None else 1.0 / float(self.fps)


class Annotations(NamedTuple):
    """The rows of a recording file, as read: frame numbers, person ids, positions (m) and, for obsmat, the
    recorded velocities (m/s; None for 4-column files)."""

    frames: np.ndarray  # (N,) float64
    ids: np.ndarray  # (N,) int64
    xy: np.ndarray  # (N, 2) float64
    velocity: np.ndarray | None  # (N, 2) float64
    format: str


class Crowd(NamedTuple):
    """The largest number of people present at one step of a scene, the first step where it happens, and that
    step's time (seconds on the recording's clock)."""

    count: int
    step: int
    time: float


def _allowed_formats() -> str:
    return ", ".join(f"{n} columns ({name})" for name, n in FORMATS.items())


def read_annotations(path: str | os.PathLike, format: str | None = None) -> Annotations:
    """Parse a 4-column or obsmat file; raises RecordingError (file and line) for anything that is not one."""
    path = pathlib.Path(path)
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        raise RecordingError(f"{path}: no such file") from None
    except OSError as e:
        raise RecordingError(f"{path}: cannot be read ({e.strerror or e})") from None
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise RecordingError(f"{path}: not a text file (byte {e.start} is not UTF-8)") from None

    expected = FORMATS[format] if format is not None else None
    rows: list[list[float]] = []
    lines: list[int] = []
    for number, line in enumerate(text.splitlines(), start=1):  # splitlines takes CRLF (obsmat) and LF alike
        cells = line.split()
        if not cells:
            continue
        if expected is None:
            if len(cells) not in FORMATS.values():
                raise RecordingError(
                    f"{path}:{number}: {len(cells)} columns found; allowed formats: {_allowed_formats()}"
                )
            expected = len(cells)
        elif len(cells) != expected:
            first = f"line {lines[0]} has {expected}" if lines else f"format {format!r} has {expected}"
            raise RecordingError(
                f"{path}:{number}: {len(cells)} columns found where {first}; allowed formats: {_allowed_formats()}"
            )
        try:
            values = [float(c) for c in cells]
        except ValueError:
            bad = next(c for c in cells if not _is_float(c))
            raise RecordingError(f"{path}:{number}: non-numeric cell {bad!r}") from None
        if not all(math.isfinite(v) for v in values):
            raise RecordingError(f"{path}:{number}: non-finite value in {line.strip()!r}")
        rows.append(values)
        lines.append(number)
    if not rows:
        raise RecordingError(f"{path}: empty file (no annotation rows)")

    table = np.asarray(rows, dtype=np.float64)
    line_of = np.asarray(lines)
    ids = table[:, 1]
    fractional = np.flatnonzero(ids != np.round(ids))
    if fractional.size:
        i = fractional[0]
        raise RecordingError(f"{path}:{line_of[i]}: person id {ids[i]:g} is not a whole number")
    frames, ids = table[:, 0], ids.astype(np.int64)
    _check_duplicates(path, frames, ids, line_of)
    fmt = next(name for name, n in FORMATS.items() if n == table.shape[1])
    if fmt == "obsmat":
        return Annotations(frames, ids, table[:, [2, 4]], table[:, [5, 7]], fmt)
    return Annotations(frames, ids, table[:, 2:4], None, fmt)


def _is_float(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _check_duplicates(path: pathlib.Path, frames: np.ndarray, ids: np.ndarray, line_of: np.ndarray) -> None:
    order = np.lexsort((frames, ids))
    same = (np.diff(frames[order]) == 0) & (np.diff(ids[order]) == 0)
    if same.any():
        k = np.flatnonzero(same)[0]
        a, b = sorted((line_of[order[k]], line_of[order[k + 1]]))
        raise RecordingError(
            f"{path}:{b}: duplicated row: frame {frames[order[k]]:g}, id {ids[order[k]]} is also on line {a}"
        )


class _Track(NamedTuple):
    id: int
    t: np.ndarray  # (n,) seconds, increasing, no gap
    xy: np.ndarray  # (n, 2)


def _tracks(ann: Annotations, frame_seconds: float, max_gap: float | None) -> tuple[list[_Track], float, float]:
    """Each person's rows in time order, cut wherever consecutive rows are more than `max_gap` seconds apart;
    returns the pieces, the usual step (s) and the gap threshold (s)."""
    order = np.lexsort((ann.frames, ann.ids))
    ids, frames, xy = ann.ids[order], ann.frames[order], ann.xy[order]
    same_person = ids[1:] == ids[:-1]
    steps = np.diff(frames)[same_person]
    # The usual step: what most consecutive annotations of one person are apart (frames are integers in practice).
    usual = float(np.median(steps)) * frame_seconds if steps.size else math.nan
    if max_gap is None:
        max_gap = GAP_FACTOR * usual if steps.size else math.inf
    t = frames * frame_seconds
    # A new piece starts at a new person or after a gap; the tolerance absorbs the rounding of frame * seconds.
    cut = ~same_person | (np.diff(t) > max_gap * (1 + 1e-9))
    starts = np.concatenate([[0], np.flatnonzero(cut) + 1, [len(t)]])
    pieces = [_Track(int(ids[a]), t[a:b], xy[a:b]) for a, b in zip(starts[:-1], starts[1:])]
    return pieces, usual, max_gap


def _median_speed(tracks: Sequence[_Track]) -> float:
    """The median over every step between consecutive annotations of a track (m/s); NaN without any step."""
    speeds = [np.linalg.norm(np.diff(tr.xy, axis=0), axis=1) / np.diff(tr.t) for tr in tracks if len(tr.t) > 1]
    return float(np.median(np.concatenate(speeds))) if speeds else math.nan


def _suggest_spacing(median: float, frame_seconds: float, step_frames: float) -> str:
    """A frame spacing at which `median` becomes a plausible walking speed: one annotation every 0.4 s (the
    ETH/UCY rate) if that fits, else the usual frame rate that comes closest to a typical speed."""
    low, high = SPEED_RANGE
    if median <= 0:
        return "no spacing helps: nobody moves between annotations"

    def speed(s: float) -> float:
        return median * frame_seconds / s

    annotated = ANNOTATION_STEP_S / step_frames
    if low <= speed(annotated) <= high and not math.isclose(annotated, frame_seconds):
        return (
            f"{annotated:.4g} s per frame ({step_frames:g} frames = {ANNOTATION_STEP_S:g} s) would give "
            f"{speed(annotated):.3g} m/s"
        )
    fits = [(abs(speed(1 / fps) - TYPICAL_SPEED), fps) for fps in COMMON_FPS if low <= speed(1 / fps) <= high]
    if not fits:
        wanted = median * frame_seconds / TYPICAL_SPEED
        return f"no usual frame rate fits: about {wanted:.4g} s per frame would give {TYPICAL_SPEED:g} m/s"
    fps = min(fits)[1]
    return f"{1 / fps:.4g} s per frame ({fps:g} fps) would give {speed(1 / fps):.3g} m/s"


def check_speed(
    path: str | os.PathLike,
    median: float,
    frame_seconds: float,
    step_frames: float,
    recorded: float | None = None,
    speed_range: tuple[float, float] = SPEED_RANGE,
) -> None:
    """Refuse a median walking speed outside `speed_range`, naming the likely cause: a wrong frame spacing (with a
    spacing that would give a plausible speed) or positions that are not metres."""
    low, high = speed_range
    if low <= median <= high:
        return
    told = f" (the file's own velocity columns give {recorded:.3g} m/s)" if recorded is not None else ""
    raise RecordingError(
        f"{path}: median walking speed {median:.3g} m/s at {frame_seconds:.4g} s per frame is outside "
        f"{low:g}-{high:g} m/s{told}: the frame spacing is likely wrong ({step_frames:g} frames per annotation = "
        f"{step_frames * frame_seconds:.3g} s); {_suggest_spacing(median, frame_seconds, step_frames)}; "
        "or the positions are not in metres"
    )


def check_recorded_velocity(
    path: str | os.PathLike, median: float, recorded: float, frame_seconds: float, step_frames: float
) -> None:
    """An obsmat file states each row's velocity (m/s), which does not depend on the frame spacing: refuse a
    spacing whose speeds from positions disagree with it by more than `VELOCITY_TOLERANCE` (a file whose velocity
    columns are all 0 states nothing and passes)."""
    if recorded <= 0 or abs(median / recorded - 1) <= VELOCITY_TOLERANCE:
        return
    agreeing = frame_seconds * median / recorded
    raise RecordingError(
        f"{path}: median walking speed {median:.3g} m/s from the positions at {frame_seconds:.4g} s per frame "
        f"disagrees with the file's own velocity columns ({recorded:.3g} m/s): the frame spacing is likely wrong; "
        f"about {agreeing:.4g} s per frame ({step_frames:g} frames = {step_frames * agreeing:.3g} s) would agree"
    )


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """One recording on a common time grid of step `dt`, one column per continuous track.

    Arrays (read-only NumPy; T steps, P tracks):

    - ``positions``: ``(T, P, 2)`` float32, metres, in the recording's own frame of reference. Row ``k`` is the time
      ``start_time + k * dt`` (seconds on the recording's clock: frame number times seconds per frame). Where a
      track is absent the entry is 0: always read positions through ``mask``.
    - ``mask``: ``(T, P)`` bool, True where track ``p`` is present at step ``k``. Each column is True on one
      contiguous run of steps: a person who left the annotation for longer than the gap threshold continues in a
      new column, since nothing is known of where they walked meanwhile.
    - ``ids``: ``(P,)`` int64, the person id of each column in the file; the pieces of a person's track split at
      a gap share the id. Columns are ordered by first appearance (then by id).

    Positions are the file's annotations interpolated linearly in time; a grid step is filled only between two
    annotations of one track (no extrapolation, never across a gap), so a track shorter than `dt` may be absent
    from the scene.
    """

    positions: np.ndarray
    mask: np.ndarray
    ids: np.ndarray
    dt: float
    start_time: float
    source: str
    seconds_per_frame: float
    format: str
    median_speed: float  # m/s, over every step between consecutive annotations of a track (before resampling)

    @property
    def num_steps(self) -> int:
        return int(self.positions.shape[0])

    @property
    def num_tracks(self) -> int:
        return int(self.positions.shape[1])

    @property
    def num_people(self) -> int:
        """Distinct person ids (a person whose track was split at a gap counts once)."""
        return int(np.unique(self.ids).size)

    @property
    def duration(self) -> float:
        """Seconds from the first to the last step of the grid."""
        return (self.num_steps - 1) * self.dt

    def velocities(self) -> np.ndarray:
        """``(T, P, 2)`` float32 m/s by finite differences: forward, ``(x[k+1] - x[k]) / dt``, so that
        ``positions[k + 1] == positions[k] + dt * velocities[k]`` along a track (up to float32 rounding);
        backward at a track's last step; 0 where the track is absent or has a single step."""
        return _velocities(self.positions, self.mask, self.dt)

    def max_crowd(self) -> Crowd:
        """The most people present at one step, and where."""
        counts = self.mask.sum(axis=1)
        step = int(np.argmax(counts)) if counts.size else 0
        return Crowd(int(counts[step]) if counts.size else 0, step, self.start_time + step * self.dt)

    def walked_positions(self) -> np.ndarray:
        """``(N, 2)`` float32: every position where someone was present on the grid (the walkable ground, as
        seen), in step order."""
        return self.positions[self.mask]


def _velocities(positions: np.ndarray, mask: np.ndarray, dt: float) -> np.ndarray:
    diff = np.zeros_like(positions)
    diff[:-1] = positions[1:] - positions[:-1]
    forward = mask[:-1] & mask[1:]  # step k and k + 1 both present
    v = np.zeros_like(positions)
    v[:-1][forward] = diff[:-1][forward] / dt
    # a track's last step (present, next absent, previous present) repeats the velocity that led to it
    last = mask.copy()
    last[:-1] &= ~mask[1:]
    last[0] = False
    last[1:] &= mask[:-1]
    ks, ps = np.nonzero(last)
    v[ks, ps] = v[ks - 1, ps]
    return v.astype(np.float32)


def resample(
    tracks: Sequence[_Track], dt: float, start_time: float, end_time: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Interpolate each track linearly onto the grid ``start_time + k * dt`` (k = 0 .. up to `end_time`); returns
    positions (T, P, 2) float32, mask (T, P) and ids (P,) of the tracks that cover at least one grid step."""
    eps = 1e-6  # in steps: a track starting at 1.0000000001 steps still covers step 1 (float rounding)
    num_steps = int(math.floor((end_time - start_time) / dt + eps)) + 1
    spans = []
    for tr in tracks:
        first = int(math.ceil((tr.t[0] - start_time) / dt - eps))
        last = int(math.floor((tr.t[-1] - start_time) / dt + eps))
        if last >= first:
            spans.append((first, tr.id, last, tr))
    spans.sort(key=lambda s: (s[0], s[1], s[2]))
    positions = np.zeros((num_steps, len(spans), 2), np.float32)
    mask = np.zeros((num_steps, len(spans)), bool)
    for p, (first, _, last, tr) in enumerate(spans):
        k = np.arange(first, last + 1)
        t = np.clip(start_time + k * dt, tr.t[0], tr.t[-1])
        positions[k, p, 0] = np.interp(t, tr.t, tr.xy[:, 0])
        positions[k, p, 1] = np.interp(t, tr.t, tr.xy[:, 1])
        mask[k, p] = True
    ids = np.asarray([s[1] for s in spans], dtype=np.int64)
    return positions, mask, ids


def load(
    spec: RecordingSpec,
    dt: float = DEFAULT_DT,
    max_gap: float | None = None,
    speed_range: tuple[float, float] = SPEED_RANGE,
) -> Scene:
    """Read `spec`'s file and resample every track onto a grid of step `dt` seconds.

    `max_gap` (seconds): consecutive annotations of a person further apart than this split the track (default:
    1.5 times the file's usual step between annotations). Raises RecordingError, naming the file (and the line
    where one applies), for a missing, unreadable, empty or malformed file, duplicated (frame, id) rows, non-finite
    values, a file without any track of two annotations, a median walking speed outside `speed_range` and, for
    obsmat, speeds from positions that disagree with the file's velocity columns (both mean a wrong frame spacing).
    """
    if not (math.isfinite(dt) and dt > 0):
        raise RecordingError(f"{spec.path}: dt must be a positive number of seconds, got {dt!r}")
    if max_gap is not None and not max_gap > 0:
        raise RecordingError(f"{spec.path}: max_gap must be a positive number of seconds, got {max_gap!r}")
    ann = read_annotations(spec.path, spec.format)
    frame_seconds = spec.frame_seconds
    tracks, usual, _ = _tracks(ann, frame_seconds, max_gap)
    median = _median_speed(tracks)
    if math.isnan(median):
        raise RecordingError(f"{spec.path}: no person has two annotations within the gap threshold; nothing moves")
    recorded = float(np.median(np.hypot(*ann.velocity.T))) if ann.velocity is not None else None
    check_speed(spec.path, median, frame_seconds, usual / frame_seconds, recorded, speed_range)
    if recorded is not None:
        check_recorded_velocity(spec.path, median, recorded, frame_seconds, usual / frame_seconds)
    t = ann.frames * frame_seconds
    start, end = float(t.min()), float(t.max())
    positions, mask, ids = resample(tracks, dt, start, end)
    for a in (positions, mask, ids):
        a.setflags(write=False)
    return Scene(
        positions=positions,
        mask=mask,
        ids=ids,
        dt=float(dt),
        start_time=start,
        source=str(spec.path),
        seconds_per_frame=frame_seconds,
        format=ann.format,
        median_speed=median,
    )


def load_file(
    path: str | os.PathLike,
    seconds_per_frame: float | None = None,
    *,
    fps: float | None = None,
    format: str | None = None,
    dt: float = DEFAULT_DT,
    max_gap: float | None = None,
) -> Scene:
    """`load(RecordingSpec(path, seconds_per_frame, fps, format), dt, max_gap)`."""
    return load(RecordingSpec(path, seconds_per_frame, fps, format), dt=dt, max_gap=max_gap)


@dataclasses.dataclass(frozen=True, eq=False)
class PackedScenes:
    """Several scenes in one padded array set, for a compiled program (S scenes; T_max and P_max the largest
    step and track counts among them):

    - ``positions``: ``(S, T_max, P_max, 2)`` float32 (0 in padding and where a track is absent);
    - ``mask``: ``(S, T_max, P_max)`` bool (False in padding);
    - ``lengths``: ``(S,)`` int32, each scene's number of steps T (its steps ``>= lengths[s]`` are padding);
    - ``num_tracks``: ``(S,)`` int32, each scene's number of tracks P;
    - ``dt``: the common step (s); ``sources``: each scene's file.
    """

    positions: np.ndarray
    mask: np.ndarray
    lengths: np.ndarray
    num_tracks: np.ndarray
    dt: float
    sources: tuple[str, ...]


def pack(scenes: Sequence[Scene]) -> PackedScenes:
    """Pad `scenes` (all on the same dt) into one `PackedScenes`."""
    if not scenes:
        raise RecordingError("pack: no scenes given")
    dts = {s.dt for s in scenes}
    if len(dts) > 1:
        raise RecordingError(f"pack: scenes on different time steps {sorted(dts)}; resample them on one dt")
    t_max = max(s.num_steps for s in scenes)
    p_max = max(s.num_tracks for s in scenes)
    positions = np.zeros((len(scenes), t_max, p_max, 2), np.float32)
    mask = np.zeros((len(scenes), t_max, p_max), bool)
    for i, s in enumerate(scenes):
        positions[i, : s.num_steps, : s.num_tracks] = s.positions
        mask[i, : s.num_steps, : s.num_tracks] = s.mask
    lengths = np.asarray([s.num_steps for s in scenes], np.int32)
    num_tracks = np.asarray([s.num_tracks for s in scenes], np.int32)
    for a in (positions, mask, lengths, num_tracks):
        a.setflags(write=False)
    return PackedScenes(positions, mask, lengths, num_tracks, scenes[0].dt, tuple(s.source for s in scenes))
