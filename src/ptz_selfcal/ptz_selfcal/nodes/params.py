"""Node parameters generated from settings dataclasses, so that each setting is defined once.

A field's Setting (ptz_selfcal/settings.py) gives the parameter's name, description and check; the
dataclass gives its default. params_from declares them, config_kwargs turns the declared values back
into the dataclass's arguments. Any node can use them: the calibrator for SessionConfig and its own
CalibratorNodeConfig, the tracker for TrackerConfig (prefix "tracker.").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass
from typing import Any

from ptz_selfcal.nodes.conversions import Param, in_range, one_of
from ptz_selfcal.settings import Setting, setting, setting_of

Check = Callable[[Any], str | None]


@dataclass(frozen=True)
class CalibratorNodeConfig:
    """The calibrator node's settings that are not the session's (persistence, the worker, diagnostics)."""

    state_dir: str = setting(
        "", "directory of the saved calibration state and zoom model ('' = no persistence)"
    )
    save_period: float = setting(30.0, "seconds between state saves (when changed)", bounds=(0.1, 86400.0))
    reoptimise_budget: float = setting(
        0.5,
        "seconds one worker re-optimisation step may take (runs beside the frames, never blocks them)",
        bounds=(0.001, 60.0),
    )
    reoptimise_period: float = setting(
        0.05, "seconds the worker waits for new keyframes", bounds=(0.001, 10.0)
    )
    diagnostics_period: float = setting(
        1.0, "seconds between DiagnosticArray messages", bounds=(0.05, 3600.0)
    )
    camera_name: str = setting(
        "",
        "name of the camera, the diagnostics' hardware_id (camera_info_manager's camera_name; '': the "
        "namespace's last component, /cam1: cam1)",
    )
    camera_info_url: str = setting(
        "",
        "camera_calibration YAML (file:// URL or a path; as cameracalibrator or `ptz-selfcal "
        "export-calibration` write it) whose K is the prior before the first calibration, in place of the "
        "nominal field of view ('': none; unreadable: a configuration error; another image size: ignored "
        "with a warning)",
    )
    stale_timeout: float = setting(
        5.0,
        "seconds without a homography after which diagnostics report STALE (also before the first one)",
        bounds=(0.1, 3600.0),
    )
    error_threshold: int = setting(
        3,
        "internal errors (frame path or worker) after which diagnostics report ERROR",
        bounds=(1, 1_000_000),
    )
    camera_info_before_calibration: str = setting(
        "prior",
        "CameraInfo before the first calibration: prior (the nominal K; FrameCalibration.status says it "
        "is not calibrated yet) or uncalibrated (K = P = 0, ROS's convention for an uncalibrated camera; "
        "FrameCalibration still carries the prior)",
        choices=("prior", "uncalibrated"),
    )
    reference_frame: str = setting(
        "",
        "frame_id of the calibration's reference (the tracking reference keyframe's camera) in the "
        "orientation transform ('': <camera_name>_selfcal_reference)",
    )
    child_frame: str = setting(
        "",
        "child_frame_id of the orientation transform, a frame of this node's own, never one of the "
        "driver's ('': <camera_name>_selfcal_optical)",
    )
    solve_slots: int = setting(
        0,
        "re-optimisations that may run at once on this machine, shared by every suite (camera) on it: "
        "a worker step waits for a free slot (0: half the machine's cores, at least 1; -1: no "
        "machine-wide limit; give every suite on a machine the same value)",
        bounds=(-1, 1024),
    )
    solve_slots_dir: str = setting(
        "",
        "directory of the machine's solve slot lock files, shared by the suites ('': "
        "/dev/shm/ptz_selfcal_solve_slots, else the temporary directory's)",
    )
    inline_solves: bool = setting(
        False,
        "solve in the frame callback before the next frame instead of in the worker (each solve completes "
        "before the next frame: a lock-step replay gives the same result every run; live, frames wait)",
    )


def params_from(config: type, *, prefix: str = "", exclude: Collection[str] = ()) -> list[Param]:
    """One parameter per field of the dataclass `config` (except `exclude`), named prefix + its name.

    Every field needs a Setting, and a number (or a tuple of numbers) its bounds: a parameter without a
    description or a check of absurd values is a TypeError here, not a surprise on a camera.
    """
    defaults = config()
    params = []
    for f in dataclasses.fields(config):
        if f.name in exclude:
            continue
        s = _setting(config, f)
        default = getattr(defaults, f.name)
        check = _check(s, default, f"{config.__name__}.{f.name}")
        value = list(default) if isinstance(default, tuple) else default  # ROS has arrays, not tuples
        bounds = None if isinstance(default, bool | str) else s.bounds  # the descriptor's range
        params.append(Param(prefix + (s.param or f.name), value, s.description, check, bounds=bounds))
    return params


def config_kwargs(
    config: type, values: Mapping[str, Any], *, prefix: str = "", exclude: Collection[str] = ()
) -> dict[str, Any]:
    """The keyword arguments of `config` from the values declared by params_from (same prefix and
    exclude): an array parameter becomes the field's tuple again, of its default's element type."""
    defaults = config()
    kwargs = {}
    for f in dataclasses.fields(config):
        if f.name in exclude:
            continue
        value = values[prefix + (_setting(config, f).param or f.name)]
        default = getattr(defaults, f.name)
        if isinstance(default, tuple):
            kind = type(default[0]) if default else (lambda v: v)
            value = tuple(kind(v) for v in value)
        kwargs[f.name] = value
    return kwargs


def _setting(config: type, f: dataclasses.Field[Any]) -> Setting:
    s = setting_of(f)
    if s is None or not s.description.strip():
        raise TypeError(f"{config.__name__}.{f.name} has no description: define it with settings.setting")
    return s


def _check(s: Setting, default: Any, where: str) -> Check | None:
    if isinstance(default, bool):
        return None  # declare_params checks the type, and a bool has no absurd value
    if isinstance(default, str):
        return one_of(*s.choices) if s.choices else None
    if s.bounds is None:
        raise TypeError(f"{where} is a number without bounds: give its setting bounds=(lo, hi)")
    check = in_range(*s.bounds)
    return _each(check, len(default)) if isinstance(default, tuple) else check


def _each(check: Check, length: int) -> Check:
    """An array parameter: its length, then check on each element."""

    def check_array(value: Any) -> str | None:
        if len(value) != length:
            return f"must have {length} values, got {list(value)}"
        for v in value:
            error = check(v)
            if error:
                return error
        return None

    return check_array
