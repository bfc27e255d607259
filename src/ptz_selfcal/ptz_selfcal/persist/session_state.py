"""The calibrator's saved state: what a restart needs to go on calibrated, as a YAML mapping.

`state_to_dict` and `state_from_dict` are pure and symmetric; `write_state` replaces the files
atomically (persist/atomic_file.py). A state that does not fit (another version, another focal
model, a damaged value) raises StateFileError: the caller starts fresh with a warning.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ptz_selfcal.online.frames import FrameOutput
from ptz_selfcal.online.incremental import IncrementalCalibrator
from ptz_selfcal.online.keyframe_solver import KeyframeBundleSolver
from ptz_selfcal.persist.atomic_file import atomic_write_text
from ptz_selfcal.persist.state_files import STATE_FILE, STATE_VERSION, ZOOM_MODEL_FILE, StateFileError
from ptz_selfcal.status import CalibrationStatus
from ptz_selfcal.zoom.model import ZoomModel, ZoomModelError


@dataclass(frozen=True)
class SavedState:
    """The parsed content of a state file."""

    image_size: tuple[int, int] | None
    reference_id: str | None
    reference_keyframe_id: int | None
    calibrator: IncrementalCalibrator | None
    keyframe_zoom: dict[int, float]
    sampled_keyframes: set[int]
    last_good: FrameOutput | None
    shared_lam: float | None
    noise_estimate: float | None
    # the lens model the evidence chose (bundle/selection.py; None: not decided yet)
    distortion_adopted: bool | None = None
    pp_varying_adopted: bool | None = None


def state_to_dict(
    image_size: tuple[int, int] | None,
    reference_id: str | None,
    last_good: FrameOutput | None,
    calibrator: IncrementalCalibrator | None,
    solver: KeyframeBundleSolver,
    keyframe_zoom: dict[int, float],
    sampled_keyframes: set[int],
    focal_model: str,
) -> dict:
    return _plain(
        {
            "version": STATE_VERSION,
            "saved_at": time.time(),
            "image_size": list(image_size) if image_size else None,
            "reference_id": reference_id,
            "reference_keyframe_id": solver.reference_keyframe_id,
            "keyframe_zoom": {int(k): float(v) for k, v in keyframe_zoom.items()},
            "sampled_keyframes": sorted(int(k) for k in sampled_keyframes),
            "last_good": None
            if last_good is None
            else {"K": last_good.K.tolist(), "D": last_good.D.tolist(), "sigma_f": float(last_good.sigma_f)},
            "calibrator": None if calibrator is None else calibrator.to_dict(),
            "shared_lam": solver.shared_lam,  # a fixed lens's distortion (None: none)
            "focal_model": focal_model,
            "noise_estimate": solver.noise_estimate,  # the eq. 27 prior's weight
            "distortion_adopted": solver.distortion_adopted,
            "pp_varying_adopted": solver.pp_varying_adopted,
        }
    )


def _choice(data: dict, key: str) -> bool | None:
    value = data.get(key)
    if value is not None and not isinstance(value, bool):
        raise StateFileError(f"{key} is {value!r}, not true, false or null")
    return value


def state_from_dict(data: dict, focal_model: str, solver: KeyframeBundleSolver) -> SavedState:
    """Parse `state_to_dict` output; StateFileError when it does not fit."""
    if data.get("version") != STATE_VERSION:
        raise StateFileError(f"state version {data.get('version')!r}, expected {STATE_VERSION}")
    saved_model = data.get("focal_model", "varying")
    if saved_model != focal_model:
        # one K for every frame is not a zoom lens's calibration, nor the reverse
        raise StateFileError(f"state saved with focal_model {saved_model!r}, configured {focal_model!r}")
    try:
        size = data.get("image_size")
        calibrator = None
        if data.get("calibrator") is not None:
            calibrator = IncrementalCalibrator.from_dict(data["calibrator"], solver=solver)
        shared_lam = data.get("shared_lam")
        shared_lam = None if shared_lam is None else float(shared_lam)
        if shared_lam is not None and not math.isfinite(shared_lam):
            raise StateFileError("shared_lam is not finite")
        noise = data.get("noise_estimate")
        ref_kf = data.get("reference_keyframe_id")
        return SavedState(
            image_size=(int(size[0]), int(size[1])) if size else None,
            reference_id=data.get("reference_id"),
            reference_keyframe_id=None if ref_kf is None else int(ref_kf),
            calibrator=calibrator,
            keyframe_zoom={
                int(k): math.nan if v is None else float(v)
                for k, v in (data.get("keyframe_zoom") or {}).items()
            },
            sampled_keyframes={int(k) for k in data.get("sampled_keyframes") or []},
            last_good=_last_good(data.get("last_good")),
            shared_lam=shared_lam,
            noise_estimate=None if noise is None or not 0.0 < float(noise) < math.inf else float(noise),
            distortion_adopted=_choice(data, "distortion_adopted"),
            pp_varying_adopted=_choice(data, "pp_varying_adopted"),
        )
    except StateFileError:
        raise
    except (KeyError, TypeError, ValueError, AttributeError, IndexError) as exc:
        raise StateFileError(f"state does not load: {type(exc).__name__}: {exc}") from exc


def _last_good(last: Any) -> FrameOutput | None:
    if not last:
        return None
    K = np.asarray(last["K"], dtype=float).reshape(3, 3)
    if not np.all(np.isfinite(K)) or K[0, 0] <= 0:
        raise StateFileError("last K is not valid")
    return FrameOutput(
        status=CalibrationStatus.CALIBRATING,
        K=K,
        D=np.asarray(last.get("D", [0.0] * 5), dtype=float).reshape(5),
        R=None,
        sigma_f=float(last.get("sigma_f", math.nan)),
        sigma_cx=math.nan,
        sigma_cy=math.nan,
        residual=math.nan,
        keyframe_id=0,
        keyframe_count=0,
        source="last_good",
    )


def write_state(state_dir: Path, data: dict, zoom_model: ZoomModel | None) -> list[str]:
    """The state (and the zoom model unless empty) replaced atomically; returns the files written."""
    atomic_write_text(state_dir / STATE_FILE, yaml.safe_dump(data, sort_keys=False))
    written = [str(state_dir / STATE_FILE)]
    if zoom_model is not None and not zoom_model.is_empty():
        zoom_model.save(state_dir / ZOOM_MODEL_FILE)
        written.append(str(state_dir / ZOOM_MODEL_FILE))
    return written


def load_zoom_model(path: Path, keep: set | None) -> tuple[ZoomModel, bool, list[str]]:
    """The saved zoom model, whether it predicts, and log lines ("WARNING: ..." first). `keep`: the live
    samples of a restored calibration's keyframes stay live; None: they all become history."""
    model, problem = ZoomModel.load_or_new(path)
    if keep is not None:
        model.commit_live(keep=keep)
    else:
        model.new_calibration()
    if problem is not None:
        return model, False, [f"WARNING: ignoring zoom model {path} ({problem}); learning a new one"]
    if model.is_empty():
        return model, False, []
    try:
        model.predict(float(np.mean(model.covered_range())))
    except (ZoomModelError, ValueError, np.linalg.LinAlgError) as exc:
        return model, False, [f"WARNING: zoom model {path} not usable ({exc})"]
    return model, True, [f"loaded zoom model from {path} (zoom range {model.covered_range()})"]


def _plain(value: Any) -> Any:
    """YAML-safe plain Python (numpy arrays and scalars converted, tuples as lists)."""
    if isinstance(value, dict):
        return {(k if isinstance(k, str | int) else str(k)): _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else value
    return value
