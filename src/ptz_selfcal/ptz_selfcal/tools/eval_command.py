"""`ptz-selfcal eval`: tools/evaluate's report with the run's mosaic (tools/mosaic.eval_mosaic) in it.

A module of its own because tools/mosaic reads bags through tools/evaluate: the command joins the two
without an import cycle between them.
"""

from __future__ import annotations

import argparse

from ptz_selfcal.tools import evaluate
from ptz_selfcal.tools.mosaic import eval_mosaic

add_arguments = evaluate.add_arguments


def run(args: argparse.Namespace) -> int:
    return evaluate.run(args, mosaic=eval_mosaic)
