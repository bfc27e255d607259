"""Settings: a dataclass field that carries its description and its valid values.

One definition per setting gives the default (the dataclass), the node parameter with its description
and its check (nodes/params.py), and the shipped parameter file's reference (checked by a test). Pure,
so that core configs (online/config.py, frontend/tracker_config.py) use it without rclpy.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

_KEY = "ptz_selfcal.setting"


@dataclass(frozen=True)
class Setting:
    """What a field means and which values it accepts."""

    description: str
    bounds: tuple[float, float] | None = None  # inclusive; for a tuple field, of each element
    choices: tuple[str, ...] = ()  # the accepted values of a string field
    param: str = ""  # the parameter's name when it is not the field's (a name users already set)


def setting(
    default: Any,
    description: str,
    *,
    bounds: tuple[float, float] | None = None,
    choices: tuple[str, ...] = (),
    param: str = "",
) -> Any:
    """A dataclass field with its default and its Setting: `x: float = setting(1.0, "...", bounds=(0, 2))`."""
    return dataclasses.field(default=default, metadata={_KEY: Setting(description, bounds, choices, param)})


def setting_of(f: dataclasses.Field[Any]) -> Setting | None:
    """The Setting of a dataclass field, None for a plain field."""
    return f.metadata.get(_KEY)
