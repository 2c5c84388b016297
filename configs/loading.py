"""One way to read a YAML file into a pydantic model, shared by every room (planners, sim, cellctl):
each failure names the file and the field, e.g. "scene.yaml: drawing.polylines[0][1]: ..."."""

from __future__ import annotations

from pathlib import Path
from typing import TypeVar

import yaml
from pydantic import BaseModel, ValidationError

M = TypeVar("M", bound=BaseModel)


def field_path(loc) -> str:
    out = ""
    for part in loc:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def format_validation_error(source: str, err: ValidationError) -> str:
    return "\n".join(f"{source}: {field_path(e['loc'])}: {e['msg']}" for e in err.errors())


def load_yaml_model(path: str | Path, model: type[M], error: type[Exception] = ValueError, what: str = "config") -> M:
    """Read and validate; raise `error` with a message naming the file and the field."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise error(f"{path}: cannot read {what}: {e.strerror or e}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise error(f"{path}: invalid YAML: {e}") from None
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise error(f"{path}: (top level): expected a mapping of {what} fields, got {type(data).__name__}")
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise error(format_validation_error(str(path), e)) from None
