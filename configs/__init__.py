"""Shipped YAML configs; the pydantic models that validate them live beside their consumers."""

from pathlib import Path

CONFIG_DIR = Path(__file__).resolve().parent
