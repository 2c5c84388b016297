"""The next-view planners the cell offers, by the name a job asks for: the one list that the job
loop, the API's request model, the CLI and the bench read. Each is imported on demand, so one
planner's dependencies never load another's."""

from __future__ import annotations

import importlib

#: name -> "module:class", in the paper's order (E-NVP, C-NBV, G-NBV), then ours
PLANNERS: dict[str, str] = {
    "enpv": "planners.enpv:ExtrapolatedNVP",
    "cnbv": "planners.cnbv:ConstrainedNBV",
    "gnbv": "planners.gnbv:GuidedNBV",
    "global": "planners.global_nbv:GlobalNBV",
}
DEFAULT_PLANNER = "gnbv"


def planner_class(name: str) -> type:
    """The planner's class (imports its module); ValueError for a name not in ``PLANNERS``."""
    try:
        module, cls = PLANNERS[name].split(":")
    except KeyError:
        raise ValueError(f"unknown planner {name!r}; choose one of {', '.join(PLANNERS)}") from None
    return getattr(importlib.import_module(module), cls)


def make_planner(name: str, cfg):
    """A fresh planner for one scan (planners keep per-scan memory); ``cfg``: PlannersConfig."""
    return planner_class(name)(cfg)
