"""What every next-view planner sees and returns, so the runner can drive any of them."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Protocol

import numpy as np

from planners.clouds import Cloud
from planners.grid import OccupancyGrid


@dataclass
class ScanState:
    step: int
    grid: OccupancyGrid
    surface: Cloud  # C_total, base frame
    drawing: Cloud  # D_total, base frame
    latest: Cloud  # C_k, base frame
    camera_pose: np.ndarray  # T_base_cam now
    initial_pose: np.ndarray  # T_base_cam of the first view
    K: np.ndarray  # 3x3 intrinsics of the camera image
    image_size: tuple[int, int]  # (width, height)
    viewpoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # camera positions so far
    # (positions (M,3), optical axes (M,3)) -> (M,) bool, False where the arm surely cannot take
    # the view (planners.motion.reach_map); None: every candidate is offered to the runner
    reachable: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None


@dataclass
class ViewPlan:
    poses: np.ndarray  # (M, 4, 4) ranked T_base_cam candidates, best first; roll is free for IK
    quality: np.ndarray  # (M,) Q of eq. 4, same order
    gain: np.ndarray  # (M,) raw gain of eq. 5
    stop: bool
    reason: str = ""  # "quality" | "frontier" | "unreachable" | "" (continue)
    target: np.ndarray | None = None  # the point the views look at (f̂ for G-NBV)
    frontier: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # frontier cell centres
    timings: dict[str, float] = field(default_factory=dict)
    tried: int = 0  # set by the runner: how many of `poses` it tried to reach before rejecting


class NextViewPlanner(Protocol):
    name: str

    def next_view(self, state: ScanState) -> ViewPlan:
        """Rank next views, or say stop. Pure computation: no device, no I/O."""

    def reject(self, plan: ViewPlan) -> None:
        """None of the plan's candidates was reachable: do not offer the same target again."""
