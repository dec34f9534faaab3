"""tgrf-render: episodes of a trained policy (RUN_DIR) and / or baseline robots as PNG frames, GIFs and MP4s."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import pathlib
import sys
import time

from tgrf_jax.cli.common import (
    Playable,
    Recovery,
    add_config_args,
    add_pretrained_arg,
    check_jax,
    check_policy_fits,
    check_seed,
    check_writable,
    command_line,
    load_playable,
    start,
)
from tgrf_jax.config import MAX_EPISODES, ConfigError

POLICY_CHOICES = ("straight", "orca")


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="tgrf-render",
        description="Render episodes as PNG frames, a GIF and (when ffmpeg is on PATH) an MP4. With a RUN_DIR "
        "(from tgrf-train) the trained policy is rendered on the run's own scenario (plus any --policy "
        "baselines); otherwise --policy baselines on a YAML config (default: the paper scenario).",
    )
    add_config_args(p, "a tgrf-train run directory, or a YAML file with env/reward sections", run_dir=True)
    p.add_argument("--policy", action="append", choices=POLICY_CHOICES, help="baseline robot (repeatable)")
    p.add_argument("--episodes", type=int, default=1, help="episodes per policy (default 1)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="episode i is episode i of tgrf-eval --seed S with as many episodes (default 0; episodes are "
        "recorded in tgrf-eval's batches of 1000, in smaller ones where 1000 episodes would exceed "
        "200,000 steps, and then only a render of at most one batch replays tgrf-eval's)",
    )
    p.add_argument("--step", type=int, default=None, help="RUN_DIR: checkpoint (update) to render; default latest")
    add_pretrained_arg(p)
    p.add_argument("--fps", type=float, default=8.0, help="GIF/MP4 frames per second (default 8 = 2x real time)")
    p.add_argument("--dpi", type=int, default=90, help="frame resolution (default 90: 648 x 720 pixels)")
    p.add_argument("--stride", type=int, default=1, help="draw every STRIDE-th step (default 1)")
    p.add_argument(
        "--rays",
        action="store_true",
        help="draw the robot's LiDAR rays and their hits (the env needs a LiDAR: env.lidar_rays > 0)",
    )
    p.add_argument("--no-frames", action="store_true", help="skip the PNG frames")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF")
    p.add_argument("--no-mp4", action="store_true", help="skip the MP4 even when ffmpeg is available")
    return p


def check(args) -> Playable:
    """Everything that can be checked without JAX; returns what to play. Raises ConfigError."""
    from tgrf_jax.render.export import ffmpeg_path

    check_jax()
    if not 1 <= args.episodes <= MAX_EPISODES:
        raise ConfigError(f"--episodes = {args.episodes} is out of range; allowed: 1 .. {MAX_EPISODES:,}")
    if not (args.fps > 0 and math.isfinite(args.fps)):
        raise ConfigError(f"--fps = {args.fps} must be > 0")
    if args.stride < 1:
        raise ConfigError(f"--stride = {args.stride} must be >= 1")
    if not 10 <= args.dpi <= 600:
        raise ConfigError(f"--dpi = {args.dpi} must be between 10 and 600")
    check_seed(args.seed)
    check_writable(args.out, "--out", directory=True)
    if args.no_frames and args.no_gif and (args.no_mp4 or ffmpeg_path() is None):
        raise ConfigError(
            "nothing to write: --no-frames and --no-gif"
            + (" and --no-mp4" if args.no_mp4 else " (and ffmpeg is not on PATH for an MP4)")
        )
    choices = "|".join(POLICY_CHOICES)
    if args.config is not None:
        src = pathlib.Path(args.config)
        if not src.exists():
            raise ConfigError(f"{args.config!r} does not exist (expected a tgrf-train run directory or a YAML config)")
        if not src.is_dir() and not args.policy:
            raise ConfigError(
                f"{args.config!r} is a config file: name the robot with --policy {choices} (a trained "
                "policy needs its RUN_DIR)"
            )
    elif not args.policy and args.pretrained is None:
        raise ConfigError(f"give a RUN_DIR, --pretrained NAME or --policy {choices}")
    playable = load_playable(args.config, args.overrides, "tgrf-render", args.pretrained)
    if args.step is not None and playable.run_dir is None:
        raise ConfigError("--step selects a checkpoint of a RUN_DIR; no RUN_DIR given")
    if args.rays and playable.env.lidar_rays == 0:
        raise ConfigError(
            "--rays draws the robot's LiDAR rays, but this env has no LiDAR (env.lidar_rays = 0); "
            "give it one, e.g. --set env.lidar_rays=72"
        )
    return playable


@command_line("tgrf-render")
def main(argv: list[str] | None, recovery: Recovery) -> int:
    """`tgrf-render`: returns the exit status (0 ok, 2 invalid input)."""
    args = parser().parse_args(argv)
    playable = check(args)

    start()
    check_policy_fits(playable)
    import jax

    from tgrf_jax.env import CrowdNavEnv
    from tgrf_jax.policies import baseline
    from tgrf_jax.render import eval_key, ffmpeg_path, record_episodes
    from tgrf_jax.render.record import episodes_per_batch

    env = CrowdNavEnv(playable.env, playable.reward)
    policies = []
    if playable.params is not None:
        from tgrf_jax.policies import make_network_for
        from tgrf_jax.policies.learned import LearnedPolicy

        policies.append(
            (
                f"pretrained {playable.pretrained}",
                "learned",
                LearnedPolicy(make_network_for(playable.config), playable.params),
            )
        )
    elif playable.run_dir is not None:
        from tgrf_jax.policies import make_network_for
        from tgrf_jax.policies.learned import LearnedPolicy
        from tgrf_jax.train.run_dir import restore_run

        recovery.from_checkpoint = f"tgrf-render {playable.run_dir} --out {args.out} --step"
        _, state = restore_run(playable.run_dir, args.step)
        policies.append(
            (
                f"learned (update {int(state.update)})",
                "learned",
                LearnedPolicy(make_network_for(playable.config), state.params),
            )
        )
    for name in args.policy or ():
        if name not in [p[1] for p in policies]:
            policies.append((name, name, baseline(name)))

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    mp4 = False if args.no_mp4 else None
    if not args.no_mp4 and ffmpeg_path() is None:
        print("tgrf-render: ffmpeg is not on PATH: writing PNG frames and GIFs only", flush=True)
    print(f"{env} on {jax.devices()[0].platform}; {args.episodes} episode(s) per policy, seed {args.seed}", flush=True)
    summary = {"env": repr(env), "seed": args.seed, "source": args.config, "episodes": []}
    n_files = 0
    per_batch = episodes_per_batch(env.default_params, env.config.lidar_rays)
    batches = -(-args.episodes // per_batch)
    for label, slug, policy in policies:
        for b in range(batches):
            first, size = b * per_batch, min(per_batch, args.episodes - b * per_batch)
            t0 = time.perf_counter()
            where = f" ({first}-{first + size - 1} of {args.episodes}, batch {b + 1}/{batches})" if batches > 1 else ""
            print(f"{label}: recording {size} episode(s){where} ...", flush=True)
            episodes = [
                dataclasses.replace(ep, index=first + ep.index)
                for ep in record_episodes(env, policy, eval_key(args.seed, b), size, label=label)
            ]
            print(f"  recorded in {time.perf_counter() - t0:.1f} s (compile included)", flush=True)
            n_files += _save(episodes, out, slug, args, mp4, summary)
    summary_path = out / "summary.json"
    summary_path.write_text(json.dumps(summary, indent=2))
    print(f"wrote {n_files + 1} files under {out}/ (index: {summary_path})")
    return 0


def _save(episodes, out: pathlib.Path, slug: str, args, mp4, summary: dict) -> int:
    """Draw and write one batch of episodes; returns the number of files written."""
    from tgrf_jax.render import save_episode

    n_files = 0
    for ep in episodes:
        t0 = time.perf_counter()
        paths = save_episode(
            ep,
            out / slug,
            frames=not args.no_frames,
            gif=not args.no_gif,
            mp4=mp4,
            fps=args.fps,
            dpi=args.dpi,
            stride=args.stride,
            show_rays=args.rays,
        )
        n_files += len(paths["frames"]) + sum(paths[k] is not None for k in ("gif", "mp4"))
        row = dict(
            ep.summary(),
            policy=slug,
            gif=paths["gif"] and str(paths["gif"]),
            mp4=paths["mp4"] and str(paths["mp4"]),
            frames=len(paths["frames"]),
            frame_dir=str(out / slug / f"ep{ep.index:03d}") if paths["frames"] else None,
        )
        summary["episodes"].append(row)
        made = ", ".join(
            x
            for x in (
                row["gif"],
                row["mp4"],
                paths["frames"] and f"{len(paths['frames'])} frames in {row['frame_dir']}",
            )
            if x
        )
        print(
            f"  episode {ep.index}: {ep.outcome} after {ep.duration:.2f} s ({ep.steps} steps), return "
            f"{ep.ret:+.2f} -> {made} [{time.perf_counter() - t0:.1f} s]",
            flush=True,
        )
    return n_files


if __name__ == "__main__":
    sys.exit(main())
