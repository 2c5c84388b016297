"""Shipped YAML configs (the pydantic models that validate them live beside their consumers), and what
rooms that may not import each other share: the Panda's description (panda.py), its batched forward
kinematics (chain.py), mount poses (poses.py) and the ChArUco board (charuco.py)."""

from pathlib import Path

CONFIG_DIR = Path(__file__).resolve().parent
