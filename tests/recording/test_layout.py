"""The Foxglove layout in the repository names only topics and fields the recordings have."""
from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

from falcon_plan.recording.channels import SCHEMAS, TOPICS

LAYOUT = Path(__file__).resolve().parents[2] / "docs" / "foxglove-layout.json"


def _panels(node: Any) -> list[str]:
    return [node] if isinstance(node, str) else _panels(node["first"]) + _panels(node["second"])


def _field(schema: dict[str, Any], path: list[str]) -> dict[str, Any]:
    for part in path:
        name, index = re.fullmatch(r"(\w+)(\[\d+\])?", part).groups()
        schema = schema["properties"][name]
        if "oneOf" in schema:
            schema = next(option for option in schema["oneOf"] if option.get("type") != "null")
        if index:
            schema = schema["items"]
    return schema


def test_the_layout_names_only_what_recordings_hold() -> None:
    layout = json.loads(LAYOUT.read_text())
    panels = _panels(layout["layout"])
    assert sorted(panels) == sorted(layout["configById"])
    paths = []
    for panel, config in layout["configById"].items():
        paths += [p["value"] for p in config.get("paths", [])]
        if "topicPath" in config:
            assert config["topicPath"] in TOPICS, panel
        for topic in config.get("topics", {}):
            assert topic in TOPICS, (panel, topic)
    assert len(paths) >= 10
    for path in paths:
        topic, _, fields = path.partition(".")
        assert topic in TOPICS, path
        leaf = _field(SCHEMAS[TOPICS[topic]], fields.split("."))
        assert leaf.get("type") in ("number", "integer") or "number" in leaf.get("type", []), path
