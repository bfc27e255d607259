"""State files of the calibrator: YAML mappings read with a clear error when unusable."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import NDArray

Array = NDArray[np.float64]


STATE_VERSION = 1
STATE_FILE = "calibration_state.yaml"
ZOOM_MODEL_FILE = "zoom_model.yaml"


class StateFileError(Exception):
    """A state file that exists but cannot be used (corrupt, wrong version, wrong camera)."""


def load_yaml_file(path: str | os.PathLike[str]) -> dict | None:
    """The mapping in a YAML file; None when the file does not exist; StateFileError when unusable."""
    path = Path(path)
    if not path.exists():
        return None
    return read_yaml_mapping(path, StateFileError)


def read_yaml_mapping(
    path: str | os.PathLike[str], error: type[Exception], what: str = "YAML mapping"
) -> dict:
    """The mapping in a YAML file; `error` saying why when the file cannot be read or holds no mapping."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        first = (str(exc).splitlines() or [""])[0]
        raise error(f"{path}: unreadable ({type(exc).__name__}: {first})") from exc
    if not isinstance(data, dict):
        raise error(f"{path}: not a {what}")
    return data


def remove_state_files(state_dir: str | os.PathLike[str]) -> list[Path]:
    """Delete the calibrator's saved state (calibration state and zoom model) in state_dir: a reset.
    Returns the files removed (none when there was no saved state)."""
    removed = []
    for name in (STATE_FILE, ZOOM_MODEL_FILE):
        path = Path(state_dir) / name
        try:
            path.unlink()
        except FileNotFoundError:
            continue
        removed.append(path)
    return removed
