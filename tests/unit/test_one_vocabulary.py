"""One vocabulary (issue 13): each status and tracking-state name is defined once, in status.py, and mapped
to the message constants once, in nodes/conversions.py. The test searches the package source for copies.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

from ptz_selfcal.nodes.conversions import (
    MSG_TO_STATUS,
    MSG_TO_TRACKING_STATE,
    STATUS_TO_MSG,
    TRACKING_STATE_TO_MSG,
)
from ptz_selfcal.status import CalibrationStatus, TrackingState

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "src" / "ptz_selfcal" / "ptz_selfcal"
MSG_DIR = REPO / "src" / "ptz_selfcal_msgs" / "msg"
VOCABULARY = PACKAGE / "status.py"
MAPPING = PACKAGE / "nodes" / "conversions.py"

NAMES = frozenset(CalibrationStatus.__members__) | frozenset(TrackingState.__members__)
ENUMS = frozenset({"CalibrationStatus", "TrackingState"})
MESSAGES = frozenset({"FrameCalibration", "HomographyStamped"})


def _terminal_name(node: ast.expr) -> str | None:
    """`a.b.C` -> "C", `C` -> "C": the name an attribute is read from."""
    if isinstance(node, ast.Name):
        return node.id
    if isinstance(node, ast.Attribute):
        return node.attr
    return None


def _enum_aliases(tree: ast.AST) -> frozenset[str]:
    """The enums' names in a module: themselves, `import ... as X` and `X = CalibrationStatus`."""
    names = set(ENUMS)
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            names |= {alias.asname for alias in node.names if alias.name in ENUMS and alias.asname}
        elif isinstance(node, ast.Assign) and _terminal_name(node.value) in ENUMS:
            names |= {target.id for target in node.targets if isinstance(target, ast.Name)}
    return frozenset(names)


def definitions(source: str) -> list[tuple[int, str]]:
    """(line, what) for each status or tracking-state name written as a string or bound to a name."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in NAMES:
            found.append((node.lineno, f"string constant {node.value!r}"))
        targets: list[ast.expr] = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, ast.AnnAssign | ast.AugAssign):
            targets = [node.target]
        for target in targets:
            for name in ast.walk(target):
                if isinstance(name, ast.Name) and name.id in NAMES:
                    found.append((name.lineno, f"name {name.id} bound (a constant or enum member)"))
    return sorted(found)


def message_mappings(source: str) -> list[tuple[int, str]]:
    """(line, what) for each use of a status or tracking-state message constant."""
    found = []
    tree = ast.parse(source)
    enums = _enum_aliases(tree)
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr in NAMES and _terminal_name(node.value) not in enums:
            found.append((node.lineno, f"message constant {_terminal_name(node.value)}.{node.attr}"))
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Name)
            and node.func.id == "getattr"
            and node.args
            and _terminal_name(node.args[0]) in MESSAGES
        ):
            found.append((node.lineno, f"getattr on {_terminal_name(node.args[0])}"))
    return sorted(found)


def _msg_constants(name: str) -> dict[str, int]:
    text = (MSG_DIR / f"{name}.msg").read_text()
    return {m[1]: int(m[2]) for m in re.finditer(r"^uint8\s+([A-Z_]+)\s*=\s*(\d+)", text, re.MULTILINE)}


def test_each_name_is_defined_once_and_mapped_once():
    problems = []
    for path in sorted(PACKAGE.rglob("*.py")):
        source = path.read_text()
        rel = path.relative_to(REPO)
        if path != VOCABULARY:
            problems += [
                f"{rel}:{line}: {what} (use ptz_selfcal.status)" for line, what in definitions(source)
            ]
        if path != MAPPING:
            problems += [
                f"{rel}:{line}: {what} (use the mappings of nodes/conversions.py)"
                for line, what in message_mappings(source)
            ]
    assert not problems, "status vocabulary defined or mapped outside its one place:\n" + "\n".join(problems)


def test_the_search_finds_every_kind_of_copy():
    """The search itself: each way of copying the vocabulary is found, the enum's own use is not."""
    copies = """
class State(enum.Enum):
    CONVERGED = "CONVERGED"
TRACKING_LOST: str = "x"
WITH_H = ("TRACKING", "NEW_KEYFRAME")
"""
    assert [line for line, _ in definitions(copies)] == [3, 3, 4, 5, 5]
    mappings = """
code = FrameCalibration.CONVERGED
same = msg.state == msg.NEW_KEYFRAME
table = {n: getattr(HomographyStamped, n) for n in names}
"""
    assert [line for line, _ in message_mappings(mappings)] == [2, 3, 4]
    allowed = """
from ptz_selfcal.status import CalibrationStatus, TrackingState
from ptz_selfcal import status
from ptz_selfcal.status import CalibrationStatus as S
T = TrackingState
ok = (S.CONVERGED, T.TEXTURELESS, CalibrationStatus.CONVERGED, status.TrackingState.RELOCALISED)
name = f"status_{TrackingState.TRACKING}"
"""
    assert definitions(allowed) == [] and message_mappings(allowed) == []


def test_the_mapping_is_the_message_constants_both_ways():
    for enum, name, to_msg, from_msg in (
        (CalibrationStatus, "FrameCalibration", STATUS_TO_MSG, MSG_TO_STATUS),
        (TrackingState, "HomographyStamped", TRACKING_STATE_TO_MSG, MSG_TO_TRACKING_STATE),
    ):
        constants = _msg_constants(name)
        assert set(enum.__members__) == set(constants), name
        assert {member.name: code for member, code in to_msg.items()} == constants
        assert {code: member for member, code in to_msg.items()} == dict(from_msg)
        assert all(member.value == member.name for member in enum)  # printed names are the message's
