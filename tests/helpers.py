"""Shared test fixtures' building blocks: scenes as YAML text, small models."""

from __future__ import annotations

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
SHARED_EXAMPLE = ROOT.parent / "shared" / "spec" / "example-scene.yaml"
EXAMPLE = SHARED_EXAMPLE if SHARED_EXAMPLE.exists() else ROOT / "scissor_cli" / "scenes" / "example.yaml"


def example_dict() -> dict:
    return yaml.safe_load(EXAMPLE.read_text())


def write_scene(tmp_path: Path, data: dict, name: str = "scene.yaml") -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def deep_update(data: dict, dotted: str, value) -> dict:
    """Set data[a][b]... for 'a.b...' (integers index lists) and return data."""
    keys = [int(k) if k.isdigit() else k for k in dotted.split(".")]
    node = data
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value
    return data
