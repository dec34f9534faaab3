"""Exporting recorded episodes: PNG frames, GIF (Pillow), MP4 (matplotlib's ffmpeg writer), inline players."""

from __future__ import annotations

import pathlib
import shutil

from tgrf_jax.render.draw import FramePainter, new_figure
from tgrf_jax.render.record import Episode


def _frame_indices(ep: Episode, stride: int) -> list[int]:
    idx = list(range(0, ep.steps + 1, stride))
    if idx[-1] != ep.steps:
        idx.append(ep.steps)  # always end on the outcome frame
    return idx


def ffmpeg_path() -> str | None:
    """The ffmpeg that matplotlib's movie writer runs (None when there is none: no MP4)."""
    from matplotlib import rcParams
    from matplotlib.animation import FFMpegWriter

    return shutil.which(rcParams["animation.ffmpeg_path"]) if FFMpegWriter.isAvailable() else None


def save_episode(
    ep: Episode,
    out_dir,
    *,
    name: str | None = None,
    frames: bool = True,
    gif: bool = True,
    mp4: bool | None = None,
    fps: float = 8.0,
    dpi: int = 90,
    stride: int = 1,
    hold_s: float = 1.5,
    **draw_kwargs,
) -> dict:
    """Write PNG frames (`<name>/frame_0000.png`...), `<name>.gif` and, when ffmpeg is on PATH, `<name>.mp4`.

    `mp4=None` writes the MP4 only if ffmpeg is found; `mp4=True` without ffmpeg raises. The last frame (the
    outcome) is held for `hold_s` seconds in the GIF and MP4. Returns {"frames": [...], "gif": path, "mp4": path}.

    PNG and GIF frames come from the painter's blitted canvas; the GIF is assembled with Pillow, quantised to 128
    colours per frame (matplotlib's PillowWriter would store full-colour frames, several times larger). The MP4
    goes through matplotlib's `FFMpegWriter`.
    """
    from PIL import Image

    if fps <= 0 or stride < 1 or dpi < 10:
        raise ValueError(f"need fps > 0, stride >= 1 and dpi >= 10, got fps={fps}, stride={stride}, dpi={dpi}")
    have_ffmpeg = ffmpeg_path() is not None
    if mp4 and not have_ffmpeg:
        raise RuntimeError("mp4=True but ffmpeg is not on PATH")
    want_mp4 = have_ffmpeg if mp4 is None else bool(mp4)
    out_dir = pathlib.Path(out_dir)
    name = name or f"ep{ep.index:03d}"
    out_dir.mkdir(parents=True, exist_ok=True)
    frame_dir = out_dir / name
    if frames:
        frame_dir.mkdir(exist_ok=True)
        for old in frame_dir.glob("frame_*.png"):
            old.unlink()

    fig, ax = new_figure(dpi=dpi)
    painter = FramePainter(ax, ep, **draw_kwargs)
    written: dict = {"frames": [], "gif": None, "mp4": None}
    gif_frames = []
    for t in _frame_indices(ep, stride):
        painter.update(t)
        rgb = painter.render_rgb()
        if frames:
            path = frame_dir / f"frame_{t:04d}.png"
            Image.fromarray(rgb).save(path)
            written["frames"].append(path)
        if gif:
            gif_frames.append(Image.fromarray(rgb).quantize(colors=128, method=Image.Quantize.MEDIANCUT))
    if want_mp4:
        written["mp4"] = _write_mp4(fig, painter, ep, out_dir / f"{name}.mp4", stride, fps, dpi, hold_s)
    if gif and gif_frames:
        gif_path = out_dir / f"{name}.gif"
        frame_ms = int(round(1000.0 / fps))
        durations = [frame_ms] * (len(gif_frames) - 1) + [max(frame_ms, int(hold_s * 1000))]
        gif_frames[0].save(
            gif_path,
            save_all=True,
            append_images=gif_frames[1:],
            duration=durations,
            loop=0,
            optimize=False,
            disposal=1,
        )
        written["gif"] = gif_path
    return written


def _write_mp4(
    fig, painter: FramePainter, ep: Episode, path: pathlib.Path, stride: int, fps: float, dpi: int, hold_s: float
) -> pathlib.Path:
    from matplotlib.animation import FFMpegWriter

    writer = FFMpegWriter(fps=fps)
    with writer.saving(fig, str(path), dpi):
        for t in _frame_indices(ep, stride):
            painter.update(t)
            writer.grab_frame()
        for _ in range(int(round(hold_s * fps))):
            writer.grab_frame()
    return path


def animate(ep: Episode, *, stride: int = 1, fps: float = 8.0, dpi: int = 72, **draw_kwargs):
    """A `matplotlib.animation.FuncAnimation` of the episode (for notebooks: `.to_jshtml()`, or `show`)."""
    from matplotlib.animation import FuncAnimation

    fig, ax = new_figure(dpi=dpi)
    painter = FramePainter(ax, ep, **draw_kwargs)
    return FuncAnimation(
        fig,
        painter.update,
        frames=_frame_indices(ep, stride),
        interval=1000.0 / fps,
        repeat=True,
        cache_frame_data=False,
    )


def to_jshtml(ep: Episode, *, stride: int = 1, fps: float = 8.0, dpi: int = 72, **draw_kwargs) -> str:
    """The episode as a self-contained HTML/JavaScript player (matplotlib's `to_jshtml`)."""
    return animate(ep, stride=stride, fps=fps, dpi=dpi, **draw_kwargs).to_jshtml(fps=fps, default_mode="once")


def show(ep: Episode, **kwargs):
    """Inline player for Jupyter: `IPython.display.HTML` of `to_jshtml(ep, **kwargs)`."""
    from IPython.display import HTML

    return HTML(to_jshtml(ep, **kwargs))


def gif_bytes(ep: Episode, **kwargs) -> bytes:
    """The episode's GIF as bytes (e.g. `IPython.display.Image(data=gif_bytes(ep))` for static viewers)."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        paths = save_episode(ep, tmp, frames=False, gif=True, mp4=False, **kwargs)
        return pathlib.Path(paths["gif"]).read_bytes()
