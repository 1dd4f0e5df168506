"""The `swimm` command line: one entry point, a sub-command per service or job (the table: swimm/commands.py).

Only the chosen command's module is imported, so ``swimm sim`` never imports torch and ``swimm --help`` imports
neither torch nor MuJoCo.
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from services import settings as settings_mod
from services.lifecycle import stop_when_launcher_exits
from services.logs import setup_logging
from services.process import ProcessSettings, configure_process
from swimm.commands import COMMANDS

log = logging.getLogger(__name__)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="swimm", description="Camera-only active target tracking over Zenoh.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, spec in COMMANDS.items():
        description = spec.help
        if spec.default_config:
            description += (
                f". A plain run reads the recipe {spec.default_config}: the defaults shown are its values where it "
                "sets them (--config FILE replaces the recipe; flags and SWIMM_* variables override either)"
            )
        command_parser = sub.add_parser(name, help=spec.help, description=description)
        command_parser.add_argument("--config", help="YAML settings file (flags and SWIMM_* variables override it)")
        command_parser.add_argument("--log-level", default=None, help="DEBUG, INFO, WARNING (env SWIMM_LOG_LEVEL)")
        if name == command:  # only the chosen command's settings are imported
            settings_mod.add_arguments(command_parser, spec.load().settings, recipe(name))
    return parser


def recipe(command: str) -> Path | None:
    """The settings file a command reads when no ``--config`` is given, or None."""
    default = COMMANDS[command].default_config
    return Path(__file__).resolve().parents[1] / default if default else None  # package data beside swimm/


def config_file(command: str, given: str | None) -> str | None:
    """The settings file of a run: ``--config`` if given, else the command's default (logged), else none."""
    default = recipe(command)
    if given or default is None:
        return given
    log.info("settings from %s (--config FILE replaces them; flags and SWIMM_* still override)",
             COMMANDS[command].default_config)  # fmt: skip
    return str(default)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command if command in COMMANDS else None)
    args = parser.parse_args(argv)
    spec = COMMANDS[args.command]
    entry = spec.load()
    setup_logging(args.command, args.log_level)
    stop_when_launcher_exits()
    try:
        settings = settings_mod.load(entry.settings, args, config_file(args.command, args.config))
        if entry.check:
            entry.check(settings)
        # Process-wide settings (switch interval, ZENOH_RUNTIME, LP_NUM_THREADS): here, once, never in library code.
        level = logging.DEBUG if spec.answers else logging.INFO
        configure_process(ProcessSettings.of(settings, renders=spec.renders), role=args.command, level=level)
    except (ValueError, FileNotFoundError, FileExistsError) as exc:  # the user's to change: said once, never retried
        log.error("%s refused its settings: %s", args.command, exc)
        return settings_mod.SETTINGS_EXIT_CODE
    try:
        result = entry.run(settings)
    except KeyboardInterrupt:
        return 130
    except Exception as exc:  # the CLI's last line of defence: a clear message, not a traceback
        if logging.getLogger().isEnabledFor(logging.DEBUG):
            raise
        log.error("%s failed: %s", args.command, exc)
        return 1
    return int(result) if isinstance(result, int) else 0
