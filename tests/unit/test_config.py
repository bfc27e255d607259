"""One source of defaults: the settings dataclasses give the calibrator's parameters, their descriptions
and their checks, and the shipped parameter file repeats exactly their defaults (issue 13)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import yaml

from ptz_selfcal.nodes.params import CalibratorNodeConfig, config_kwargs, params_from
from ptz_selfcal.online.config import SessionConfig
from ptz_selfcal.settings import setting, setting_of
from ptz_selfcal.tools.launch import default_params_file

CONFIGS = (CalibratorNodeConfig, SessionConfig)

# The calibrator's parameter names before its parameters were generated: a user's file still works.
NAMES_USERS_SET = {
    "nominal_hfov_deg",
    "nominal_focal_px",
    "state_dir",
    "save_period",
    "reoptimise_budget",
    "reoptimise_period",
    "reoptimise_min_interval",
    "reoptimise_max_duty",
    "min_rotation_deg",
    "min_keyframes",
    "max_keyframes",
    "bundle_adjustment",
    "ba_principal_point",
    "pp_prior_sigma_px",
    "focal_model",
    "converged_max_sigma_f",
    "converged_max_lens_model_change",
    "estimate_distortion",
    "ba_max_points_per_pair",
    "diagnostics_period",
}


def calibrator_params():
    return [p for config in CONFIGS for p in params_from(config)]


def test_every_setting_is_a_described_parameter_with_a_unique_name():
    params = calibrator_params()
    names = [p.name for p in params]
    assert len(names) == len(set(names))
    assert set(names) >= NAMES_USERS_SET, NAMES_USERS_SET - set(names)
    assert len(params) == sum(len(dataclasses.fields(c)) for c in CONFIGS)
    for p in params:
        assert p.description.strip(), p.name
        if isinstance(p.default, int | float) and not isinstance(p.default, bool):
            assert p.check is not None, p.name


def test_the_node_and_the_session_agree_on_the_solve_schedule():
    """The session's defaults are the node's shipped values (they disagreed: 0 s and 1.0 against 0.1 s
    and 0.5), under the parameter names users set."""
    defaults = {p.name: p.default for p in calibrator_params()}
    assert defaults["reoptimise_min_interval"] == SessionConfig().min_solve_period_s == 0.1
    assert defaults["reoptimise_max_duty"] == SessionConfig().max_solve_duty == 0.5
    assert "min_solve_period_s" not in defaults and "max_solve_duty" not in defaults


def test_parameter_values_give_back_the_config():
    for config in CONFIGS:
        values = {p.name: p.default for p in params_from(config)}
        assert config(**config_kwargs(config, values)) == config()
    values = {p.name: p.default for p in params_from(SessionConfig)}
    values["reoptimise_min_interval"] = 2.5
    assert SessionConfig(**config_kwargs(SessionConfig, values)).min_solve_period_s == 2.5


def test_the_shipped_yaml_sets_exactly_the_defaults():
    """Every calibrator key of config/ptz_selfcal.yaml is a parameter, with the dataclass default and
    type (rclpy refuses a double parameter set to an integer), and every parameter is listed."""
    listed = yaml.safe_load(default_params_file().read_text())["/**/calibrator"]["ros__parameters"]
    params = {p.name: p for p in calibrator_params()}
    assert set(listed) == set(params), set(listed) ^ set(params)
    for name, value in listed.items():
        default = params[name].default
        assert type(value) is type(default) and value == default, (name, value, default)


def out_of_range(lo, hi):
    """Values just outside [lo, hi] (integers for an integer range), and NaN."""
    if isinstance(lo, int) and isinstance(hi, int):
        return [lo - 1, hi + 1]
    return [lo - max(abs(lo), 1.0) * 1e-3, hi + max(abs(hi), 1.0) * 1e-3, math.nan]


def test_the_checks_accept_the_range_and_refuse_what_is_outside_it():
    checked = 0
    for config in CONFIGS:
        for f, p in zip(dataclasses.fields(config), params_from(config), strict=True):
            s = setting_of(f)
            if s.choices:
                assert all(p.check(c) is None for c in s.choices), p.name
                assert "must be one of" in p.check("bogus"), p.name
                checked += 1
            if s.bounds is None:
                continue
            lo, hi = s.bounds
            assert p.check(p.default) is None and p.check(lo) is None and p.check(hi) is None, p.name
            for bad in out_of_range(lo, hi):
                assert "must be in" in p.check(bad), (p.name, bad)
            checked += 1
    assert checked >= 25


@dataclasses.dataclass(frozen=True)
class _Tracker:  # a TrackerConfig-like dataclass: a tuple field, a string with choices, a prefix
    grid: tuple[int, int] = setting((8, 5), "cells", bounds=(1, 100))
    source: str = setting("warped", "source", choices=("warped", "frame"))
    internal: float = 0.5  # not a parameter


def test_tuple_fields_are_arrays_checked_element_by_element_and_a_prefix_names_them():
    params = {p.name: p for p in params_from(_Tracker, prefix="tracker.", exclude={"internal"})}
    assert set(params) == {"tracker.grid", "tracker.source"}
    grid = params["tracker.grid"]
    assert grid.default == [8, 5] and grid.check([8, 5]) is None
    assert "must have 2 values" in grid.check([8, 5, 1])
    assert "must be in" in grid.check([8, 0])
    values = {"tracker.grid": [4, 3], "tracker.source": "frame"}
    kwargs = config_kwargs(_Tracker, values, prefix="tracker.", exclude={"internal"})
    assert kwargs == {"grid": (4, 3), "source": "frame"}


def test_a_field_without_a_description_or_bounds_cannot_become_a_parameter():
    with pytest.raises(TypeError, match="internal has no description"):
        params_from(_Tracker)

    @dataclasses.dataclass
    class Unbounded:
        x: float = setting(1.0, "a number with no range")

    with pytest.raises(TypeError, match="without bounds"):
        params_from(Unbounded)
