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


class _NoDuplicateKeys(yaml.SafeLoader):
    """yaml.safe_load's loader, refusing a key given twice in one mapping: YAML keeps the last one
    without a word, and a cell would run on a setting its operator thought was changed."""


def _mapping(loader: _NoDuplicateKeys, node: yaml.MappingNode, deep: bool = False) -> dict:
    first: dict = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=deep)
        try:
            line = first.get(key)
        except TypeError:  # an unhashable key: construct_mapping says so
            continue
        if line is not None:
            raise yaml.constructor.ConstructorError(
                "while constructing a mapping", node.start_mark,
                f"found duplicate key {key!r} (first given on line {line + 1})", key_node.start_mark)
        first[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=deep)


_NoDuplicateKeys.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping)


def safe_load(text: str):
    """yaml.safe_load, with a key given twice in one mapping an error (yaml.YAMLError)."""
    return yaml.load(text, Loader=_NoDuplicateKeys)  # noqa: S506 - a SafeLoader subclass


def load_yaml_model(path: str | Path, model: type[M], error: type[Exception] = ValueError, what: str = "config") -> M:
    """Read and validate; raise `error` with a message naming the file and the field."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as e:
        raise error(f"{path}: cannot read {what}: {e.strerror or e}") from None
    try:
        data = safe_load(text)
    except yaml.YAMLError as e:
        raise error(f"{path}: invalid YAML: {e}") from None
    data = {} if data is None else data
    if not isinstance(data, dict):
        raise error(f"{path}: (top level): expected a mapping of {what} fields, got {type(data).__name__}")
    try:
        return model.model_validate(data)
    except ValidationError as e:
        raise error(format_validation_error(str(path), e)) from None
