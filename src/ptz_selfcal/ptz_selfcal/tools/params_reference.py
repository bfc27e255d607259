"""`ptz-selfcal params [--out FILE]`: the reference of every node's parameters, made from the nodes' own
declarations (name, default, range or choices, description), so that it cannot drift from them.
docs/parameters.md is its output; a unit test keeps that file current.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

# (node name, module, the module's functions or lists of Param beside PARAMS)
NODES: tuple[tuple[str, str, tuple[str, ...]], ...] = (
    ("frame_ingest", "ptz_selfcal.nodes.frame_ingest", ()),
    ("homography_tracker", "ptz_selfcal.nodes.homography_tracker", ("tracker_params",)),
    ("calibrator", "ptz_selfcal.nodes.calibrator", ()),
    ("mosaic", "ptz_selfcal.nodes.mosaic_node", ()),
)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=Path, help="write the reference (Markdown) here instead of printing it")


def run(args: argparse.Namespace) -> int:
    text = reference()
    if args.out is None:
        print(text, end="")
    else:
        args.out.write_text(text)
        print(f"wrote {args.out}")
    return 0


def node_params(module_name: str, extra: Sequence[str] = ()) -> list[Any]:
    """The Params a node declares: its PARAMS and the lists its extra functions return."""
    module = importlib.import_module(module_name)
    params = list(module.PARAMS)
    for name in extra:
        made: Callable[[], list[Any]] | list[Any] = getattr(module, name)
        params += made() if callable(made) else list(made)
    return params


def reference() -> str:
    lines = [
        "# Parameters",
        "",
        "Made by `ptz-selfcal params --out docs/parameters.md` from the nodes' declarations; the shipped",
        "`src/ptz_selfcal/config/ptz_selfcal.yaml` sets exactly these defaults. Ranges and choices are",
        "checked at start-up and through the parameter service (a value outside them is refused).",
        "",
    ]
    for node, module, extra in NODES:
        lines += [
            f"## {node}",
            "",
            "| parameter | default | range / choices | description |",
            "|---|---|---|---|",
        ]
        for p in node_params(module, extra):
            lines.append(f"| `{p.name}` | {_value(p.default)} | {_limits(p)} | {_cell(p.description)} |")
        lines.append("")
    return "\n".join(lines)


def _value(value: Any) -> str:
    if isinstance(value, str):
        return f'`"{value}"`'
    if isinstance(value, bool):
        return f"`{str(value).lower()}`"
    return f"`{value}`"


def _limits(p: Any) -> str:
    choices = getattr(p.check, "choices", None)
    if choices:
        return ", ".join(f"`{c}`" for c in choices)
    bounds = getattr(p.check, "bounds", None) or p.bounds
    if bounds is None:
        return ""
    return f"[{_number(bounds[0])}, {_number(bounds[1])}]"


def _number(x: float) -> str:
    return f"{x:g}"


def _cell(text: str) -> str:
    return " ".join(text.split()).replace("|", "\\|")
