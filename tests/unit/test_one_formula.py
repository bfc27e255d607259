"""The division model's corner-shift conversion (corner shift as a fraction of the half-diagonal <-> lam)
is written once, in camera/distortion.py; everything else calls it. Searched in the package's code
(comments and strings left out), so a copy of the expression under any variable names fails here."""

from __future__ import annotations

import io
import re
import tokenize
from pathlib import Path

import pytest

from ptz_selfcal.camera import distortion

PACKAGE = Path(distortion.__file__).resolve().parents[1]
HOME = Path(distortion.__file__).resolve()
ONE = r"1(?:\.0*)?"
NAME = r"[A-Za-z_][\w.]*"
RHO = rf"(?:{NAME}\s*\*\s*{NAME}|\w*rho\w*|{NAME}\s*\*\*\s*2)"

# each written-out form of the conversion, whatever the names
PATTERNS = {
    # lam = -s / ((1 + s) rho^2)
    "lam from shift": re.compile(rf"-\s*(?P<s>{NAME})\s*/\s*\(\s*\(\s*{ONE}\s*\+\s*(?P=s)\s*\)\s*\*"),
    # s = 1 / (1 + lam rho^2) - 1
    "shift from lam": re.compile(rf"{ONE}\s*/\s*\(\s*{ONE}\s*\+\s*{NAME}\s*\*\s*{RHO}\s*\)\s*-\s*{ONE}\b"),
    # d lam / d s = -1 / ((1 + s)^2 rho^2)
    "d lam / d shift": re.compile(rf"\(\s*{ONE}\s*\+\s*{NAME}\s*\)\s*\*\*\s*2\s*\*\s*{RHO}"),
    # d s / d lam = -rho^2 / (1 + lam rho^2)^2
    "d shift / d lam": re.compile(
        rf"{RHO}\s*\)?\s*/\s*\(\s*{ONE}\s*\+\s*{NAME}\s*\*\s*{RHO}\s*\)\s*\*\*\s*2"
    ),
    # rho^2 of the corner: (half-diagonal / f)^2
    "corner rho^2": re.compile(rf"\(\s*[\w.]*half_diagonal\s*/\s*{NAME}\s*\)\s*\*\*\s*2"),
}

# the copies this test replaced (lens/estimation.py, bundle/adjust.py, camera/distortion.py)
COPIES = {
    "lam from shift": [
        "return -s / ((1.0 + s) * rho2)",
        "-shift_fraction / ((1.0 + shift_fraction) * rho * rho)",
    ],
    "shift from lam": [
        "s = 1.0 / (1.0 + lam * rho2) - 1.0",
        "return float(1.0 / (1.0 + lam * rho * rho) - 1.0)",
    ],
    "d lam / d shift": ["dlam_ds = -1.0 / ((1.0 + s) ** 2 * rho2)", "(-1.0 / ((1.0 + shift) ** 2 * rho2))"],
    "d shift / d lam": ["w = w / (rho2 / (1.0 + lam * rho2) ** 2) ** 2"],
    "corner rho^2": ["rho2 = (self.half_diagonal / f) ** 2", "(curve.half_diagonal / focals) ** 2"],
}


def code_only(text: str) -> str:
    """The source with comments and string literals (docstrings) blanked, line structure kept."""
    lines = text.splitlines(keepends=True)
    out = [list(line) for line in lines]
    for tok in tokenize.generate_tokens(io.StringIO(text).readline):
        if tok.type not in (tokenize.COMMENT, tokenize.STRING):
            continue
        (r0, c0), (r1, c1) = tok.start, tok.end
        for r in range(r0, r1 + 1):
            row = out[r - 1]
            start = c0 if r == r0 else 0
            end = c1 if r == r1 else len(row)
            for c in range(start, end):
                if row[c] != "\n":
                    row[c] = " "
    return "".join("".join(row) for row in out)


def package_sources() -> list[Path]:
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


@pytest.mark.parametrize("name", sorted(PATTERNS))
def test_the_search_catches_the_old_copies(name: str) -> None:
    for copy in COPIES[name]:
        assert PATTERNS[name].search(copy), (name, copy)


def test_the_one_definition_is_in_camera_distortion() -> None:
    code = code_only(HOME.read_text())
    for name in ("lam from shift", "shift from lam", "d lam / d shift", "d shift / d lam"):
        assert len(PATTERNS[name].findall(code)) == 1, name
    for fn in (
        distortion.lambda_of_corner_shift,
        distortion.corner_shift_of_lambda,
        distortion.lambda_of_corner_shift_derivative,
        distortion.corner_shift_of_lambda_derivative,
    ):
        assert callable(fn)


def test_the_corner_shift_formula_is_written_nowhere_else() -> None:
    found = []
    for path in package_sources():
        if path == HOME:
            continue
        code = code_only(path.read_text())
        for name, pattern in PATTERNS.items():
            for m in pattern.finditer(code):
                line = code.count("\n", 0, m.start()) + 1
                found.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {name}: {m.group(0)!r}")
    assert not found, "call camera/distortion.py instead:\n" + "\n".join(found)
