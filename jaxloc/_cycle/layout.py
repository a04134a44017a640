"""The layout of a localization cycle: its steps, moves and distinct robot placements.

One table per strategy, and nowhere else. Indexing used throughout jaxloc:

- robots `0, 1, 2` are the ground robots C1 (PTZ camera), C2, C3 (omnidirectional);
- a *step* is one snapshot of the team (one formation). The sequential strategy has
  4 steps (start, after C2 moved, after C3 moved, after C1 moved); the concurrent
  strategy has 3 (start, after move 1 of C2 and C3, after move 2);
- moves, in order: sequential `[C2, C3, C1]`; concurrent `[C2 move 1, C3 move 1,
  C2 move 2, C3 move 2]`;
- a *placement* is one distinct pose a robot occupies during the cycle: a robot that
  does not move between two steps keeps its placement. Sequential: 6 placements,
  concurrent: 7. Placement 0 is C1 at the start of the cycle, the world frame `W`.
  The overhead camera sees each placement as one distinct point.
"""

import numpy as np


STRATEGIES = ("sequential", "concurrent")
CAMERAS = ("C", "C1", "C2", "C3")
"""The four robots (and their cameras) in the order of every per-robot array: the
climbing robot C, then the ground robots C1, C2, C3."""

_STEPS = {"sequential": 4, "concurrent": 3}
_MOVERS = {"sequential": (1, 2, 0), "concurrent": (1, 2, 1, 2)}
_MOVE_STARTS = {"sequential": (0, 1, 2), "concurrent": (0, 0, 1, 1)}
_PLACEMENTS = {
    "sequential": ((0, 1, 2), (0, 3, 2), (0, 3, 4), (5, 3, 4)),
    "concurrent": ((0, 1, 2), (0, 3, 4), (0, 5, 6)),
}
# Reference robot of each step's mutual localization: sequential, the robot that has
# been still the longest (the new formation is joined to the chain through it).
_REFERENCES = {"sequential": (0, 2, 0, 1), "concurrent": (0, 0, 0)}


def check_strategy(strategy: str) -> str:
    """`strategy` if it is one of `STRATEGIES`, else a `ValueError` naming it."""
    if strategy not in STRATEGIES:
        raise ValueError(f"`strategy` must be one of {STRATEGIES}; got {strategy!r}.")
    return strategy


def num_steps(strategy: str) -> int:
    """Number of formations (snapshots) in one cycle of `strategy`."""
    return _STEPS[check_strategy(strategy)]


def num_moves(strategy: str) -> int:
    """Number of odometry-measured moves in one cycle of `strategy`."""
    return len(_MOVERS[check_strategy(strategy)])


def moving_robot(strategy: str) -> np.ndarray:
    """Index of the robot that makes each move, shape `(moves,)`."""
    return np.array(_MOVERS[check_strategy(strategy)])


def move_start_step(strategy: str) -> np.ndarray:
    """Step at which each move starts (it ends at the next step), shape `(moves,)`."""
    return np.array(_MOVE_STARTS[check_strategy(strategy)])


def placement_ids(strategy: str) -> np.ndarray:
    """Index of the distinct placement (pose) each robot occupies at each step, shape
    `(steps, 3)`. Placement 0 is C1 at the start of the cycle (the world frame)."""
    return np.array(_PLACEMENTS[check_strategy(strategy)])


def num_placements(strategy: str) -> int:
    """Number of distinct robot placements of a cycle (6 sequential, 7 concurrent)."""
    return int(placement_ids(strategy).max()) + 1


def first_sighting(strategy: str) -> tuple[np.ndarray, np.ndarray]:
    """`(step, robot)` where each placement first occurs, two arrays `(placements,)`."""
    ids = placement_ids(strategy)
    steps, robots = [], []
    for p in range(num_placements(strategy)):
        k, r = np.argwhere(ids == p)[0]
        steps.append(k)
        robots.append(r)
    return np.array(steps), np.array(robots)


def reference_robots(strategy: str) -> tuple[int, ...]:
    """Reference robot of each step's mutual localization, one per step."""
    return _REFERENCES[check_strategy(strategy)]


def other_robots(robot: int) -> tuple[int, int]:
    """The two ground robots other than `robot`, in increasing order."""
    a, b = (i for i in range(3) if i != robot)
    return a, b
