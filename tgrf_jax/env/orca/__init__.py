"""ORCA (optimal reciprocal collision avoidance) for all agents of a scene at once, with RVO2's semantics: one call of
``RVO::Agent::computeNewVelocity`` per agent, optionally with static obstacles processed as RVO2 does.

kernel (solve, solve_with_info) builds the half-planes with obstacle_tree, agent_lines and obstacle_lines, and
solves for the velocities with linear_program, obstacle_lp and linear_program3; numerics holds shared helpers.
How and why it is vectorised: docs/design.md.
"""

from tgrf_jax.env.orca.kernel import CPU_BLOCK, WHOLE_BATCH, default_block, solve, solve_with_info
from tgrf_jax.env.orca.numerics import RVO_EPSILON
from tgrf_jax.env.orca.obstacle_tree import ObstacleTable, process_obstacles

__all__ = [
    "CPU_BLOCK",
    "RVO_EPSILON",
    "WHOLE_BATCH",
    "ObstacleTable",
    "default_block",
    "process_obstacles",
    "solve",
    "solve_with_info",
]
