"""`ptz-selfcal`: the one command-line entry point (DESIGN.md section 6).

Each sub-command lives in its own module under ptz_selfcal.tools with `add_arguments(parser)` and
`run(args) -> int`; modules are imported only when their command runs, so `--help` stays fast.
Expected failures (bad files, bad arguments) raise CliError or BagError: one line on stderr, exit 2.
"""

from __future__ import annotations

import argparse
import importlib
import sys

COMMANDS: dict[str, tuple[str, str]] = {
    "launch": ("ptz_selfcal.tools.launch", "start the node suite for a live camera"),
    "play": ("ptz_selfcal.tools.play", "publish a bag's messages (in place of `ros2 bag play`)"),
    "record": ("ptz_selfcal.tools.record", "record topics to a new mcap bag (in place of `ros2 bag record`)"),
    "run": ("ptz_selfcal.tools.run", "replay a bag through the real nodes and record every output"),
    "eval": ("ptz_selfcal.tools.eval_command", "run + compare with encoders and ground truth: report, plots"),
    "synth": ("ptz_selfcal.tools.synth", "render a PTZ camera bag from an equirectangular panorama"),
    "mosaic": (
        "ptz_selfcal.tools.mosaic",
        "panoramic mosaic (PNG) of a bag, or of a folder of stills, through its calibration",
    ),
    "export-calibration": (
        "ptz_selfcal.tools.export_calibration",
        "write camera_calibration YAML per zoom setting from a saved zoom model",
    ),
    "reset": ("ptz_selfcal.tools.reset", "drop a camera's calibration and saved state: start afresh"),
    "params": (
        "ptz_selfcal.tools.params_reference",
        "print every node's parameters: defaults, ranges, descriptions",
    ),
}


class CliError(Exception):
    """An expected user-facing failure: printed as one line, exit status 2."""


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ptz-selfcal", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module_name, help_text) in COMMANDS.items():
        cmd = sub.add_parser(name, help=help_text, description=help_text)
        cmd.set_defaults(command_module=module_name)
        if name in (sys.argv[1:] if argv is None else argv)[:1]:  # only the chosen command's module
            importlib.import_module(module_name).add_arguments(cmd)
    return parser


def main(argv: list[str] | None = None) -> int:
    from ptz_selfcal.tools.bagio import BagError

    # The command modules raise ptz_selfcal.tools.cli.CliError; under `python -m` this file is
    # __main__, a different module object, so catch the class of the importable module.
    cli_error = importlib.import_module("ptz_selfcal.tools.cli").CliError
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    module = importlib.import_module(args.command_module)
    try:
        return int(module.run(args) or 0)
    except (cli_error, BagError) as exc:
        print(f"ptz-selfcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"ptz-selfcal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
