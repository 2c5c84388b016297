"""Cut-path parameters: defined with the other planner parameters (planners.config) so that
configs/planners.yaml validates them in one place; re-exported here for the cutpath package."""

from planners.config import CutPathConfig, TorchConfig

__all__ = ["CutPathConfig", "TorchConfig"]
