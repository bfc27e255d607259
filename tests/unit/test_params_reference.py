"""docs/parameters.md is the parameter reference the nodes' declarations make: current, and complete."""

from __future__ import annotations

from pathlib import Path

from ptz_selfcal.tools.params_reference import NODES, node_params, reference

ROOT = Path(__file__).resolve().parents[2]


def test_docs_parameters_is_what_the_declarations_make() -> None:
    text = (ROOT / "docs" / "parameters.md").read_text()
    assert text == reference(), "docs/parameters.md is stale: ptz-selfcal params --out docs/parameters.md"


def test_every_declared_parameter_has_a_row_with_its_range() -> None:
    text = reference()
    for node, module, extra in NODES:
        section = text.split(f"## {node}\n", 1)[1].split("\n## ", 1)[0]
        for p in node_params(module, extra):
            row = next(line for line in section.splitlines() if line.startswith(f"| `{p.name}` |"))
            bounds = getattr(p.check, "bounds", None) or p.bounds
            if bounds is not None and not isinstance(p.default, bool | str):
                assert f"[{bounds[0]:g}, {bounds[1]:g}]" in row, row
            for choice in getattr(p.check, "choices", None) or ():
                assert f"`{choice}`" in row, row
