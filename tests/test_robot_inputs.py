"""The Navigator against what a robot can feed it: readings beyond what float32 and physics allow are refused (the
robot's own state and goal) or dropped and counted (detections), and a network output that is not finite never
reaches the command or the recurrent state, in every runtime."""

from __future__ import annotations

import math

import jax
import numpy as np
import pytest

from tgrf_jax.config import TrainConfig
from tgrf_jax.deploy import Detection, Navigator, NonFiniteDecision, PolicySource, export
from tgrf_jax.deploy.navigator import HUMAN_SPEED_MAX, POSITION_BOUND, ROBOT_SPEED_FACTOR, reduce_heading
from tgrf_jax.policies import make_network_for

pytest.importorskip("onnxruntime")
pytest.importorskip("jax2onnx")

PRETRAINED = "table1-const_vel-tgrf"
ROBOT = (0.0, -4.0, math.pi / 2, 0.0, 0.0)
GOAL = (0.0, 4.0)
HUMANS = [Detection((1.0, -3.0), (0.5, 0.0), 0.3), Detection((-1.5, -2.0), (0.0, -0.5), 0.4)]


@pytest.fixture(scope="module")
def nav() -> Navigator:
    return Navigator(PRETRAINED)


def fresh(nav: Navigator, *readings) -> list:
    """The decisions of a trip started anew on these readings (each robot, goal, humans)."""
    nav.reset()
    return [nav.act(*r) for r in readings]


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(robot=(1e30, -6.0, math.pi / 2, 0.0, 0.0)), r"robot_state position \(1e\+30, -6\) m is beyond"),
        (dict(robot=(POSITION_BOUND * 1.01, 0.0, 0.0, 0.0, 0.0)), r"robot_state position .* beyond \+-10000 m"),
        (dict(goal=(1e39, 0.0)), r"goal \(1e\+39, 0\) m is beyond \+-10000 m"),
        (dict(goal=(0.0, -2e4)), r"goal .* beyond"),
        (dict(robot=(0.0, -4.0, 0.0, 4.9, 0.0)), r"robot_state velocity \(4.9, 0\) m/s: its speed 4.9 m/s is over 1.5"),
        (dict(robot=(0.0, -4.0, 0.0, 0.0, 1.6)), r"faster than the robot drives"),
        (dict(robot=(0.0, -4.0, np.inf, 0.0, 0.0)), r"robot_state must be finite"),
    ],
)
def test_implausible_robot_state_and_goal_are_refused_and_change_nothing(nav, change, message):
    reference = fresh(nav, (ROBOT, GOAL, HUMANS), (ROBOT, GOAL, HUMANS))
    nav.reset()
    nav.act(ROBOT, GOAL, HUMANS)
    state = nav.state.copy()
    with pytest.raises(ValueError, match=message):
        nav.act(change.get("robot", ROBOT), change.get("goal", GOAL), HUMANS)
    np.testing.assert_array_equal(nav.state, state)
    # the refused reading left no trace: the next one is decided as in the trip without it
    np.testing.assert_array_equal(nav.act(ROBOT, GOAL, HUMANS).command, reference[1].command)
    # and a trip that starts with a refused reading is a fresh trip
    nav.reset()
    with pytest.raises(ValueError, match=message):
        nav.act(change.get("robot", ROBOT), change.get("goal", GOAL), HUMANS)
    np.testing.assert_array_equal(nav.act(ROBOT, GOAL, HUMANS).command, reference[0].command)


def test_robot_speed_within_the_bound_is_accepted(nav):
    v = 0.99 * ROBOT_SPEED_FACTOR * nav.env_config.robot_v_max
    (d,) = fresh(nav, ((0.0, -4.0, math.pi / 2, 0.0, v), GOAL, HUMANS))
    assert np.all(np.isfinite(d.command))


@pytest.mark.parametrize(
    "bad",
    [
        Detection((1e39, 1.0), (0.0, 0.0), 0.3),  # inf in float32
        Detection((2.0, 1e38), (0.0, 0.0), 0.3),  # beyond the map bound, finite in float32
        Detection((1.0, -3.5), (1e38, 0.0), 0.3),  # its predictions would overflow
        Detection((1.0, -3.5), (100.0, 0.0), 0.3),  # no person runs at 100 m/s
        Detection((1.0, -3.5), (0.0, HUMAN_SPEED_MAX * 1.01), 0.3),
        Detection((500.0, -4000.0), (0.0, 0.0), 300.0),  # millimetres read as metres
        Detection((1.0, -3.5), (0.0, 0.0), -0.3),
        Detection((1.0, -3.5), (np.nan, 0.0), 0.3),
    ],
)
def test_implausible_detections_are_dropped_and_counted(nav, bad, caplog):
    (reference,) = fresh(nav, (ROBOT, GOAL, HUMANS))
    before = nav.dropped_total
    nav.reset()
    with caplog.at_level("WARNING", logger="tgrf_jax.deploy.navigator"):
        d = nav.act(ROBOT, GOAL, HUMANS[:1] + [bad] + HUMANS[1:])
    assert (d.num_detected, d.num_dropped, d.num_used) == (3, 1, 2)
    assert nav.dropped_total == before + 1
    assert "dropped 1 of 3 detections (1 with a" in caplog.text
    np.testing.assert_array_equal(d.command, reference.command)
    np.testing.assert_array_equal(d.action, reference.action)


def test_headings_are_reduced_modulo_two_pi():
    # a unicycle policy reads the heading (the holonomic ones keep pi/2)
    nav = Navigator("unicycle-gentle-tgrf")
    for heading in (1e12, -1e9, 7.0, -3.0):
        reduced = reduce_heading(heading)
        assert math.pi / 2 - math.pi <= reduced < math.pi / 2 + math.pi
        # float64 reduction: 2 pi's rounding grows with the number of turns (1e-4 rad at 1e12 rad)
        tolerance = 1e-9 + 1e-15 * abs(heading)
        assert math.isclose(math.sin(reduced), math.sin(heading), abs_tol=tolerance)
        assert math.isclose(math.cos(reduced), math.cos(heading), abs_tol=tolerance)
        (raw,) = fresh(nav, ((0.0, -4.0, heading, 0.0, 0.0), GOAL, HUMANS))
        (ref,) = fresh(nav, ((0.0, -4.0, reduced, 0.0, 0.0), GOAL, HUMANS))
        assert np.all(np.isfinite(raw.command))
        np.testing.assert_array_equal(raw.command, ref.command)
    assert reduce_heading(math.pi / 2) == math.pi / 2


# ------------------------------------------------------------------------------------------ non-finite output

GST_HUMANS = [Detection((1.0, -3.0), (0.5, 0.0), 0.3, id=7), Detection((-1.5, -2.0), (0.0, -0.5), 0.4, id=3)]
# The sabotaged network below overflows to NaN when the robot moves fast enough along and across the goal
# direction (goal straight ahead in +y: goal-frame velocity (vy, -vx)); a standing robot decides normally.
OVERFLOW_ROBOT = (0.0, -4.0, math.pi / 2, -0.8, 0.8)


@pytest.fixture(scope="module")
def sabotaged(tmp_path_factory) -> PolicySource:
    """An untrained recurrent HH Attn with GST predictions whose finite weights overflow on some plausible readings:
    the robot-velocity rows of one embedding channel are 3e38 (inf from speeds near 1 m/s), and the two layers
    that read the embedding read that channel with weight 0 (inf * 0 = NaN; a finite 1e38 * 0 = 0, so slower
    readings decide normally whatever the other weights)."""
    config = TrainConfig.from_dict(
        {
            "env": {"num_humans": 3, "predictor": "gst", "human_policy": "social_force"},
            "network": {"name": "hh_attn", "size": "small"},
        }
    )
    params = jax.device_get(make_network_for(config).init(jax.random.PRNGKey(0)))
    layers = params["params"]
    kernel = np.array(layers["robot_linear"]["kernel"])
    kernel[0:2, 0] = 3e38
    layers["robot_linear"]["kernel"] = kernel
    encoder = np.array(layers["node_encoder"]["kernel"])
    encoder[0] = 0.0
    layers["node_encoder"]["kernel"] = encoder
    query = np.array(layers["rh_query"]["kernel"])
    query[0] = 0.0
    layers["rh_query"]["kernel"] = query
    source = PolicySource(config, params, {"test": "sabotaged"})
    out = export(source, tmp_path_factory.mktemp("sabotaged") / "policy", say=lambda m: None)
    return source, out


@pytest.mark.parametrize("runtime", ["jax", "onnx", "stablehlo"])
def test_non_finite_output_raises_and_changes_nothing(sabotaged, runtime):
    source, directory = sabotaged
    nav = Navigator(directory, runtime=runtime)
    trip = [(ROBOT, GOAL, GST_HUMANS), ((0.0, -3.9, math.pi / 2, 0.0, 0.4), GOAL, GST_HUMANS)]
    reference = fresh(nav, *trip)
    assert not np.array_equal(reference[0].command, reference[1].command)

    nav.reset()
    nav.act(*trip[0])
    state = nav.state.copy()
    with pytest.raises(NonFiniteDecision, match=r"not finite \(action \[nan, nan\].*left as they were"):
        nav.act(OVERFLOW_ROBOT, GOAL, GST_HUMANS)
    np.testing.assert_array_equal(nav.state, state)
    # the GST history did not take the refused frame either: the next reading is decided as in the unbroken trip
    after = nav.act(*trip[1])
    np.testing.assert_array_equal(after.command, reference[1].command)
    np.testing.assert_array_equal(after.action, reference[1].action)

    nav.reset()
    with pytest.raises(NonFiniteDecision):
        nav.act(OVERFLOW_ROBOT, GOAL, GST_HUMANS)
    assert not nav.state.any()
    np.testing.assert_array_equal(nav.act(*trip[0]).command, reference[0].command)
