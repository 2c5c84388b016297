"""Cutting path for the gas torch from the reconstructed drawing (issue: drawing -> cut path).

drawing cloud -> skeleton graph (junctions, free ends, branches; `graph`) -> per branch a smoothed,
evenly spaced curve on the surface with torch poses (`geometry`) -> IK along each branch with
continuity, the cut timed by the travel speed, approach and retract (`plan`) -> `CutPath`, written
as cut_path.json / cut_path.csv (`model`).
"""

from planners.cutpath.config import CutPathConfig, TorchConfig
from planners.cutpath.geometry import Surface, smooth_resample, torch_poses
from planners.cutpath.graph import DrawingGraph, drawing_graph
from planners.cutpath.model import REASONS, SCHEMA_VERSION, Branch, CutPath
from planners.cutpath.plan import build_cut_path, plan_cut, plan_cut_path, solve_branch, torch_kinematics

__all__ = [
    "Branch",
    "CutPath",
    "CutPathConfig",
    "DrawingGraph",
    "REASONS",
    "SCHEMA_VERSION",
    "Surface",
    "TorchConfig",
    "build_cut_path",
    "drawing_graph",
    "plan_cut",
    "plan_cut_path",
    "smooth_resample",
    "solve_branch",
    "torch_kinematics",
    "torch_poses",
]
