"""Static obstacles in the env: scenarios that draw layouts, the fixed layout of env.obstacles, collisions with
obstacles as an outcome of their own, occlusion, and the LiDAR in the observation."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tgrf_jax.config import OBSTACLE_SCENARIOS, ConfigError, EnvConfig
from tgrf_jax.env import OBSTACLE_COLLISION, CrowdNavEnv, sensing
from tgrf_jax.env import obstacles as obstacles_lib
from tgrf_jax.env.scenarios.sampling import choose, with_obstacles

# Social Force humans keep these tests independent of the ORCA solver's obstacle lines (tested on their own).
SF = dict(human_policy="social_force")


@pytest.fixture(scope="module", params=OBSTACLE_SCENARIOS)
def scenario_resets(request):
    env = CrowdNavEnv(dict(scenario=request.param, **SF))
    obs, state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(7), 256))
    return request.param, env, obs, state


def test_scenario_layouts_keep_starts_goals_and_spawns_out_of_obstacles(scenario_resets):
    name, env, obs, state = scenario_resets
    p = env.default_params
    clear = jax.vmap(obstacles_lib.clearance)
    assert np.all(np.asarray(state.obstacles.num_vertices).sum(-1) > 0), f"{name}: an episode without obstacles"
    robot_room = np.asarray(clear(jnp.stack([state.robot.pos, state.robot.goal], 1), state.obstacles))
    assert robot_room.min() >= float(p.robot_radius), f"{name}: robot start/goal {robot_room.min():.3f} m from a wall"
    humans = np.asarray(clear(state.humans.pos, state.obstacles)) - np.asarray(state.humans.radius)
    active = np.asarray(state.humans.active)
    assert humans[active].min() >= 0.0, f"{name}: {np.mean(humans[active] < 0):.2%} humans in a wall"
    assert int(np.asarray(state.obstacles_dropped).sum()) == 0  # the scenarios never need the fallback


def test_crowded_draws_put_no_start_or_goal_inside_an_obstacle():
    # 60 humans on random_obstacles' circle: many draws find no candidate clear of every other human, and the
    # fallback may then pick one close to a human, never one in a box (whose goal no route reaches).
    env = CrowdNavEnv(dict(scenario="random_obstacles", num_humans=60, **SF))
    p = env.default_params
    p = p.replace(goal_change_prob=jnp.float32(1.0), goal_change_interval=p.dt)  # a new goal every step

    @jax.jit
    def play(key):
        _, state = jax.vmap(env.reset, in_axes=(0, None))(jax.random.split(key, 32), p)
        still = jnp.zeros((32, env.action_size))

        def step(state, k):
            state = jax.vmap(env.step_env, in_axes=(0, 0, 0, None))(jax.random.split(k, 32), state, still, p)[1]
            return state, state.humans.goal

        goals = jax.lax.scan(step, state, jax.random.split(jax.random.fold_in(key, 1), 8))[1]
        return state, jnp.concatenate([state.humans.pos[None], state.humans.goal[None], goals])

    state, points = play(jax.random.key(3))  # the starts, the first goals, then 8 new goals each
    room = np.asarray(jax.vmap(jax.vmap(obstacles_lib.clearance), in_axes=(0, None))(points, state.obstacles))
    room = room - np.asarray(state.humans.radius)[None]
    active = np.broadcast_to(np.asarray(state.humans.active)[None], room.shape)
    assert room[active].min() >= 0.0, f"a start or goal {-room[active].min():.2f} m inside an obstacle"


def test_a_fallback_draw_may_crowd_a_human_or_a_wall_but_never_overlaps_an_obstacle():
    wall = obstacles_lib.from_polygons([[(0.0, -5.0), (0.0, 5.0)]])
    radius, gap = jnp.float32(0.3), 0.1
    # x is the distance from the wall: A overlaps it, B keeps less than the gap, C keeps all of it
    candidates = jnp.array([[0.25, 0.0], [0.35, 0.0], [2.0, 0.0]])
    spacing = jnp.array([10.0, -0.3, -0.4])  # room from the other humans (squared metres): none keeps its gap
    margin = with_obstacles(spacing, candidates, radius, wall, gap)
    # B: the wall's gap weighs like the humans' (C crowds a human more), but A's overlap rules it out
    assert np.allclose(choose(candidates, margin), [0.35, 0.0])


def test_the_intersections_cross_corridor_is_one_way_and_streams_persist():
    env = CrowdNavEnv(dict(scenario="intersection", **SF))
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(7), 64))[1]
    goal, active = np.asarray(state.humans.goal), np.asarray(state.humans.active)
    across = np.abs(goal[..., 0]) > np.abs(goal[..., 1])
    flows = [set(np.sign(goal[e, across[e] & active[e], 0]).tolist()) for e in range(goal.shape[0])]
    assert all(len(f) == 1 for f in flows if f)  # one way in each episode
    assert {f.pop() for f in flows if f} == {-1.0, 1.0}  # either way over episodes
    own = ~across & active
    assert set(np.sign(goal[..., 1][own]).tolist()) == {-1.0, 1.0}  # the robot's corridor: both ways
    # a human at its goal is respawned on its own stream: same corridor, same direction
    from tgrf_jax.env.scenarios.obstacle_layouts import INTERSECTION

    for e in range(8):
        layout = jax.tree_util.tree_map(lambda a, e=e: a[e], state.obstacles)
        for j in np.flatnonzero(active[e])[:3]:
            start, new_goal = INTERSECTION.respawn(
                jax.random.key(int(e * 100 + j)), env.default_params, layout, state.humans.pos[e, j], goal[e, j], 0.0, 4
            )
            axis = 0 if across[e, j] else 1
            assert np.all(np.sign(np.asarray(new_goal)[:, axis]) == np.sign(goal[e, j, axis]))
            assert np.all(np.abs(np.asarray(new_goal)[:, axis]) > np.abs(np.asarray(new_goal)[:, 1 - axis]))


def test_the_corridors_two_streams_walk_separate_lanes_that_fit_between_the_walls():
    from tgrf_jax.env.scenarios.obstacle_layouts import _LANE_OFFSET

    env = CrowdNavEnv(dict(scenario="corridor", **SF))
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(3), 64))[1]
    half_width = np.asarray(state.obstacles.vertices)[:, 1, 0, 0]  # the right-hand wall at x = +w
    assert half_width.min() >= 1.75 and half_width.max() <= 2.5  # two lanes of the largest ORCA humans fit
    active = np.asarray(state.humans.active)
    for points in (np.asarray(state.humans.pos), np.asarray(state.humans.goal)):
        direction = np.sign(np.asarray(state.humans.goal)[..., 1])
        x = points[..., 0] * direction  # distance right of the centre line, facing the way the human walks
        assert x[active].min() >= _LANE_OFFSET - 1e-5  # the streams never share the centre line
        lane_edge = np.broadcast_to(half_width[:, None] - 0.6, x.shape)  # clear of the walls
        assert np.all(np.abs(points[..., 0])[active] <= lane_edge[active] + 1e-5)


def test_scenario_layouts_vary_between_episodes(scenario_resets):
    name, env, obs, state = scenario_resets
    vertices = np.asarray(state.obstacles.vertices)
    assert len({v.tobytes() for v in vertices}) > 100, f"{name}: the layout is (almost) always the same"


def test_open_space_env_has_no_obstacle_slots_and_no_scan():
    env = CrowdNavEnv(dict(num_humans=5))
    obs, state = env.reset(jax.random.key(0))
    assert state.obstacles.num_vertices.shape == (0,) and obs.lidar.shape == (0,)
    assert env.config.obstacle_slots == 0


def _wall_env(**extra):
    """The robot drives up the y axis into a wall across x = [-3, 3] at y = -4 (no humans)."""
    return CrowdNavEnv(
        dict(
            num_humans=0,
            predictor="none",
            scenario="frontal_approach",
            obstacles=[[[3.0, -4.0], [-3.0, -4.0]]],
            **extra,
        )
    )


def test_driving_into_a_wall_is_an_obstacle_collision():
    env = _wall_env()
    obs, state = env.reset(jax.random.key(0))
    step = jax.jit(lambda k, s, a: env.step_env(k, s, a, env.default_params))
    outcome = 0
    for t in range(40):
        obs, state, reward, terminated, truncated, info = step(jax.random.key(t), state, jnp.array([0.0, 1.0]))
        if terminated:
            outcome = int(info.outcome)
            break
    assert outcome == OBSTACLE_COLLISION
    # contact when the robot's disc reaches the wall: start at y = -6, wall at -4, radius 0.3, 0.25 m per step
    assert t + 1 == int(np.ceil((2.0 - 0.3) / 0.25))
    assert float(reward) == pytest.approx(float(env.default_params.reward.r_col))


def test_a_fixed_layout_on_the_robot_start_is_dropped_and_counted():
    # a box around the lane robots' start (0, -6): removed in every episode, never a robot inside a wall
    box = [[-1.0, -7.0], [1.0, -7.0], [1.0, -5.0], [-1.0, -5.0]]
    env = CrowdNavEnv(dict(num_humans=0, predictor="none", scenario="frontal_approach", obstacles=[box]))
    obs, state = jax.vmap(env.reset)(jax.random.split(jax.random.key(0), 8))
    assert np.all(np.asarray(state.obstacles.num_vertices) == 0)
    assert np.all(np.asarray(state.obstacles_dropped) == 1)


def test_lidar_sees_the_wall_at_its_distance():
    env = _wall_env(lidar_rays=4)
    obs, state = env.reset(jax.random.key(0))
    # holonomic robots face +y (heading pi/2): ray 0 straight at the wall 2 m ahead, ray 2 away from it
    start = np.asarray(state.robot.pos)
    assert float(obs.lidar[0]) == pytest.approx(abs(-4.0 - start[1]), abs=1e-5)
    assert float(obs.lidar[2]) == pytest.approx(float(env.default_params.sensor_range))


def test_occlusion_hides_a_human_behind_a_wall():
    from helpers import hand_state

    for occlusion, seen in ((False, 1), (True, 0)):
        env = CrowdNavEnv(
            dict(num_humans=1, predictor="none", occlusion=occlusion, obstacles=[[[-2.0, 1.0], [2.0, 1.0]]])
        )
        state = hand_state(robot_pos=[0.0, 0.0], robot_goal=[0.0, 5.0], human_pos=[[0.0, 2.5]])
        state = state.replace(obstacles=obstacles_lib.from_polygons([[[-2.0, 1.0], [2.0, 1.0]]]))
        obs = sensing.observe(state, env.default_params, None, env.visible(state, env.default_params))
        assert int(obs.human_mask.sum()) == seen


def test_the_doorways_people_leave_in_waves_one_way():
    from tgrf_jax.env.scenarios.obstacle_layouts import DOORWAY

    env = CrowdNavEnv(dict(scenario="doorway", **SF))
    state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(5), 32))[1]
    door_y = np.asarray(state.obstacles.vertices)[:, 0, 1, 1]  # the left wall's inner end
    pos, goal = np.asarray(state.humans.pos), np.asarray(state.humans.goal)
    crossing = np.sign(pos[..., 1] - door_y[:, None]) != np.sign(goal[..., 1] - door_y[:, None])
    assert crossing.any() and np.all(pos[..., 1][crossing] > door_y[:, None].repeat(pos.shape[1], 1)[crossing])

    def crossing_share(t):
        layout = jax.tree_util.tree_map(lambda a: a[0], state.obstacles)
        keys = jax.random.split(jax.random.key(1), 600)
        draw = jax.vmap(lambda k: DOORWAY.respawn(k, env.default_params, layout, pos[0, 0], goal[0, 0], t, 1))
        start, end = (np.asarray(a)[:, 0] for a in draw(keys))
        return np.mean(np.sign(start[:, 1] - door_y[0]) != np.sign(end[:, 1] - door_y[0]))

    # during a wave (the first 6 s of every 30) a third of the fresh humans cross; between waves, none
    assert 0.25 < crossing_share(2.0) < 0.42 and 0.25 < crossing_share(31.0) < 0.42
    assert crossing_share(10.0) == 0.0 and crossing_share(59.0) == 0.0


def test_mix_with_obstacle_scenarios_draws_both_kinds():
    env = CrowdNavEnv(dict(scenario="mix", mix_scenarios=["circle_crossing", "doorway"], num_humans=4, **SF))
    obs, state = jax.jit(jax.vmap(env.reset))(jax.random.split(jax.random.key(3), 64))
    with_walls = np.asarray(state.obstacles.num_vertices).sum(-1) > 0
    door = np.asarray(state.scenario) == env.config.drawn_scenarios.index("doorway")  # 1: the mix's second
    assert 0 < door.sum() < 64 and np.array_equal(with_walls, door)


def _ngon(n):
    """A regular n-gon of radius 1 about (5, 5), counter-clockwise."""
    return [[5 + np.cos(a), 5 + np.sin(a)] for a in np.linspace(0, 2 * np.pi, n, endpoint=False)]


@pytest.mark.parametrize(
    "env, error",
    [
        (dict(obstacles=[[[0, 0], [1, 1], [1, 0]]]), r"env.obstacles\[0\] = .* is clockwise"),
        (dict(obstacles=[[[0, 0]]]), r"env.obstacles\[0\] = .* has 1 vertices"),
        (dict(obstacles=[[[0, 0], [float("nan"), 1]]]), r"env.obstacles\[0\] = .* has non-finite coordinates"),
        (dict(obstacles=[[[0, 0], [2, 0], [0, 2], [2, 2]]]), r"env.obstacles\[0\] = .* intersects itself"),
        (dict(lidar_rays=100000), r"env.lidar_rays = 100000 is out of range"),
        (dict(lidar_rays=-1), r"env.lidar_rays = -1 is out of range"),
        (dict(scenario="mix", mix_scenarios=["corridor", "corridor"]), r"env.mix_scenarios"),
        (dict(scenario="mix", mix_scenarios=["hallway"]), r"env.mix_scenarios\[0\] = 'hallway' is not a scenario"),
        (
            dict(scenario="mix", mix_scenarios=["corridor", "doorway"], scenario_weights=[1, 1, 1]),
            r"env.scenario_weights has 3 value\(s\); allowed: 2",
        ),
        # capacities (config.MAX_POLYGON_VERTICES, MAX_OBSTACLE_SLOTS, MAX_OBSTACLE_EDGES), checked before compiling
        (dict(obstacles=[_ngon(33)]), r"env.obstacles\[0\] = .* has 33 vertices; allowed: at most 32"),
        (dict(obstacles=[[[0, 0], [1, 0]]] * 33), r"env.obstacles has 33 polygons; allowed: at most 32 \(32 obstacle"),
        (
            dict(scenario="doorway", obstacles=[[[0, 0], [1, 0]]] * 25),
            r"env.obstacles has 25 polygons; allowed: at most 24 \(32 obstacle slots in all, of which the scenario "
            r"draws into 8\)",
        ),
        (
            dict(scenario="corridor", obstacles=[_ngon(16)]),
            r"env.obstacles makes 9 obstacle slots of 16 vertices \(each slot holds as many as the longest polygon\), "
            r"144 edge slots; allowed: at most 128",
        ),
    ],
)
def test_bad_obstacle_settings_are_config_errors(env, error):
    with pytest.raises(ConfigError, match=error):
        EnvConfig(**env)


def test_the_largest_obstacle_capacities_are_allowed():
    assert EnvConfig(obstacles=[_ngon(32)] * 4).obstacle_slots * 32 == 128
    assert EnvConfig(scenario="random_obstacles", obstacles=[[[0, 0], [1, 0]]] * 24).obstacle_slots == 32
