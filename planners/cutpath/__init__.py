"""Cutting path for the gas torch from the reconstructed drawing.

drawing cloud -> skeleton graph (junctions, free ends, branches; `graph`), and the pieces of a broken
line (`pieces`) -> per branch a smoothed, evenly spaced curve on the surface with torch poses
(`geometry`) -> a ladder graph within the torch's tilt tolerances, batched IK, lazy collision checks,
the cheapest continuous joint path, split into cuttable runs with the gaps and their reasons
(`ladder`) -> each run timed, with approach and retract (`plan`) -> `CutPath`, written as
cut_path.json / cut_path.csv (`model`).
"""

from planners.cutpath.config import CutPathConfig, TorchConfig
from planners.cutpath.geometry import Surface, smooth_resample, torch_poses
from planners.cutpath.graph import DrawingGraph, drawing_graph
from planners.cutpath.model import REASONS, SCHEMA_VERSION, Branch, CutPath, Gap
from planners.cutpath.ladder import GAP_REASONS
from planners.cutpath.plan import build_cut_path, plan_cut, plan_cut_path, torch_kinematics

__all__ = [
    "Branch",
    "CutPath",
    "CutPathConfig",
    "DrawingGraph",
    "GAP_REASONS",
    "Gap",
    "REASONS",
    "SCHEMA_VERSION",
    "Surface",
    "TorchConfig",
    "build_cut_path",
    "drawing_graph",
    "plan_cut",
    "plan_cut_path",
    "smooth_resample",
    "torch_kinematics",
    "torch_poses",
]
