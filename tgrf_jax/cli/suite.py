"""`tgrf-eval --suite DIR`: a policy on every scenario x crowd size, with fixed test seeds, as one table.

Every row plays the same compiled evaluation: the env is `scenario: mix` over every scenario (the crowd scenarios
and those with static obstacles) with one-hot `scenario_weights` (which plays exactly that scenario's episodes)
and the crowd size set by `active_humans_min = active_humans_max`, all traced params. The capacity is the largest
size; a trained MLP keeps the capacity it was trained with (its input has that shape), and larger crowds are left
out of its table, while attention networks (HH Attn, DS-RNN) play every size with the same weights.

When the ETH/UCY recordings are in the user data directory (`tgrf-data fetch eth-ucy`), the five real scenes of
the leave-one-scene-out benchmark follow as rows (eth, hotel, univ, zara1, zara2: each fold's test files), played
by a second compiled evaluation: `scenario: replay` over the five folds with one-hot `replay_weights`, people
moving exactly along their recordings, no augmentation; the capacity's slots play the people nearest the robot.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import pathlib
import time

SUITE_SIZES = (5, 10, 20, 30)
RECORDED = "recorded"  # the humans column of the real scenes' rows: the people of the recording
SYNTHETIC_HUMANS = "orca"  # how the synthetic rows' humans move for a policy trained among replayed recordings
# Columns of the Markdown table (the CSV holds every metric).
TABLE_COLUMNS = (
    ("success_rate", "SR", "{:.1%}"),
    ("collision_rate", "coll.", "{:.1%}"),
    ("timeout_rate", "timeout", "{:.1%}"),
    ("nav_time", "NT (s)", "{:.2f}"),
    ("path_length", "PL (m)", "{:.2f}"),
    ("spl", "SPL", "{:.3f}"),
    ("itr_disc", "ITR disc (%)", "{:.2f}"),
    ("min_dist_human", "min dist (m)", "{:.3f}"),
    ("personal_space_compliance", "PS (%)", "{:.1f}"),
    ("min_ttc", "min TTC (s)", "{:.2f}"),
    ("jerk_mean", "jerk (m/s^3)", "{:.2f}"),
    ("time_stalled", "stalled (s)", "{:.2f}"),
    ("stuck_rate", "humans stuck (%)", "{:.2f}"),
)


def suite_env_config(env_config, capacity: int, scenarios=None):
    """The suite's env: every scenario (or those of `scenarios`) selectable by weights, `capacity` human slots.
    The humans move as the config says; a policy trained among recordings walked exactly (`human_policy:
    replay`, which has no model of its own to move synthetic crowds) meets ORCA humans, the simulator's default,
    and the recordings a config was trained on are left to the real scenes' rows."""
    from tgrf_jax.config import SCENARIOS

    human_policy = SYNTHETIC_HUMANS if env_config.human_policy == "replay" else env_config.human_policy
    return dataclasses.replace(
        env_config,
        scenario="mix",
        mix_scenarios=SCENARIOS if scenarios is None else tuple(scenarios),
        num_humans=capacity,
        active_humans_min=None,
        active_humans_max=None,
        scenario_weights=None,
        human_policy=human_policy,
        replay_files=None,
        replay_weights=None,
    )


def real_env_config(env_config, capacity: int):
    """The suite's env for the real scenes: every fold's test files selectable by `replay_weights`, the recorded
    people played unchanged (no augmentation, not reacting), `capacity` slots holding the people nearest the robot;
    the recordings have no walls of their own, so the config's obstacles are left out."""
    from tgrf_jax.pedestrians import FOLDS

    return dataclasses.replace(
        env_config,
        scenario="replay",
        mix_scenarios=None,
        scenario_weights=None,
        replay_files=FOLDS,
        replay_weights=None,
        replay_augment=False,
        replay_overflow="nearest",
        human_policy="replay",
        num_humans=capacity,
        active_humans_min=None,
        active_humans_max=None,
        obstacles=None,
    )


def missing_recordings(data_dir=None) -> list[str]:
    """The files of the real scenes' rows that are not in the data directory (all present: [])."""
    from tgrf_jax.pedestrians import ETH_UCY, FOLDS

    return [
        str(e.spec(data_dir).path)
        for e in ETH_UCY
        if e.fold in FOLDS and not pathlib.Path(e.spec(data_dir).path).is_file()
    ]


def check_recordings() -> None:
    """Raises ConfigError unless every file of the real scenes' rows is in the data directory."""
    from tgrf_jax.config import ConfigError

    missing = missing_recordings()
    if missing:
        raise ConfigError(
            f"the suite's real scenes need the ETH/UCY recordings; {len(missing)} are missing (first: {missing[0]}): "
            "`tgrf-data fetch eth-ucy` downloads them"
        )


def run_suite(
    config,
    policies: dict,
    out_dir,
    *,
    episodes: int,
    seed: int,
    sizes=SUITE_SIZES,
    capacity=None,
    thumbnails: bool = True,
    real: bool | None = None,
    scenarios=None,
    log=print,
) -> list[dict]:
    """Evaluate each of `policies` (name -> Policy) on every scenario (or those of `scenarios`) x size, and on the
    real scenes (`real`: None plays them when the recordings are in the data directory); writes `suite.md`,
    `suite.csv` and `thumbnails/<scenario>.png` under `out_dir` and returns the rows."""
    import jax
    import jax.numpy as jnp

    from tgrf_jax.config import SCENARIOS
    from tgrf_jax.env import CrowdNavEnv
    from tgrf_jax.evaluate import evaluate
    from tgrf_jax.pedestrians import FOLDS

    scenarios = SCENARIOS if scenarios is None else tuple(scenarios)
    capacity = max(sizes) if capacity is None else capacity
    if scenarios:
        env = CrowdNavEnv(suite_env_config(config.env, capacity, scenarios), config.reward)
        base = env.default_params
        if config.env.human_policy == "replay":
            log(
                "suite: the policy was trained among recorded people walking their recordings; the synthetic rows' "
                f"humans move as env.human_policy = {SYNTHETIC_HUMANS!r}, the simulator's default"
            )
    played = [n for n in sizes if n <= capacity]
    skipped = [n for n in sizes if n > capacity]
    if skipped and scenarios:
        log(f"suite: crowd sizes {skipped} exceed the policy's {capacity} human slots; left out")
    missing = missing_recordings()
    if real is None:
        real = not missing
        if missing:
            log(
                f"suite: the real scenes ({', '.join(FOLDS)}) are left out: {len(missing)} of their recordings are not "
                f"in the data directory (first: {missing[0]}); `tgrf-data fetch eth-ucy` downloads them"
            )
    elif real:
        check_recordings()
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    total = (len(scenarios) * len(played) + (len(FOLDS) if real else 0)) * len(policies)
    done = 0
    if not scenarios and not real:
        raise ValueError("the suite has no rows: no scenarios and not the real scenes")
    if scenarios:
        log("suite: compiling the evaluation program (one per policy, shared by every row), then playing the rows ...")
    t0 = time.perf_counter()

    def play(env, params, scenario, humans):
        nonlocal done
        for label, policy in policies.items():
            result = evaluate(env, policy, jax.random.key(seed), episodes, params=params)
            done += 1
            rows.append(dict(scenario=scenario, humans=humans, policy=label, **result.to_dict()))
            log(
                f"[{done}/{total}] {scenario:22s} {humans:>8} humans  {label:10s} SR {result.success_rate:6.1%}  "
                f"coll. {result.collision_rate:6.1%}  ({time.perf_counter() - t0:.0f} s)"
            )

    def thumbnail(env, params, name):
        if thumbnails:
            _thumbnail(env, next(iter(policies.values())), params, seed, out / "thumbnails" / f"{name}.png", name)

    for s, name in enumerate(scenarios):
        weights = jnp.zeros(len(scenarios), jnp.float32).at[s].set(1.0)
        for n in played:
            play(env, params_for(base, weights, n), name, n)
        thumbnail(env, params_for(base, weights, min(10, capacity)), name)
    if real:
        log("suite: the real scenes: compiling their evaluation program (one per policy), then playing them ...")
        real_env = CrowdNavEnv(real_env_config(config.env, capacity), config.reward)
        for s, name in enumerate(FOLDS):
            params = real_env.default_params.replace(replay_weights=jnp.zeros(len(FOLDS), jnp.float32).at[s].set(1.0))
            play(real_env, params, name, RECORDED)
            thumbnail(real_env, params, name)
    _write_tables(rows, out)
    pictures = len(scenarios) + (len(FOLDS) if real else 0)
    log(f"wrote {out / 'suite.md'}, {out / 'suite.csv'}" + (f" and {pictures} thumbnails" if thumbnails else ""))
    return rows


def params_for(base, weights, n):
    """`base` playing the scenario of one-hot `weights` with exactly n humans."""
    import jax.numpy as jnp

    return base.replace(scenario_weights=weights, active_humans_min=jnp.float32(n), active_humans_max=jnp.float32(n))


def _thumbnail(env, policy, params, seed, path: pathlib.Path, title: str):
    """One episode's frame after 6 s (or its end), trails of the last 6 s, as a small PNG."""
    from tgrf_jax.render import eval_key, record_episodes
    from tgrf_jax.render.draw import draw_frame, new_figure

    ep = record_episodes(env, policy, eval_key(seed), 1, params)[0]
    fig, ax = new_figure(size=(4.0, 4.4), dpi=60)
    draw_frame(ax, ep, min(ep.steps, 24), trail_steps=24, show_legend=False)
    ax.set_title(title, fontsize=10)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)


def _cell(value, fmt):
    return "n/a" if value is None or (isinstance(value, float) and math.isnan(value)) else fmt.format(value)


def _write_tables(rows: list[dict], out: pathlib.Path) -> None:
    header = "| scenario | humans | policy | " + " | ".join(label for _, label, _ in TABLE_COLUMNS) + " |"
    lines = [header, "|" + "---|" * (len(TABLE_COLUMNS) + 3)]
    for r in rows:
        lines.append(
            f"| {r['scenario']} | {r['humans']} | {r['policy']} | "
            + " | ".join(_cell(r[f], fmt) for f, _, fmt in TABLE_COLUMNS)
            + " |"
        )
    (out / "suite.md").write_text("\n".join(lines) + "\n")
    with open(out / "suite.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
