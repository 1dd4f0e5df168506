"""The `swimm` command line: one entry point, a sub-command per service or job.

Each sub-command names its settings dataclass and its run function by
import path, so ``swimm sim`` never imports torch and ``swimm --help``
imports neither torch nor MuJoCo.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services import settings as settings_mod
from services.lifecycle import stop_when_launcher_exits
from services.logs import setup_logging
from services.process import ProcessSettings, configure_process

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Command:
    settings: str  # "module:Class" of the settings dataclass
    run: str  # "module:function" taking the settings
    help: str
    default_config: str = ""  # a settings file beside the packages, read when no --config is given
    check: str = ""  # "module:function" refusing bad settings before the command starts anything (exit 2)
    renders: bool = False  # may render a World whose settings are not its own (in-process envs): LP_NUM_THREADS
    answers: bool = False  # its output is its answer: the process settings' line only at DEBUG


COMMANDS: dict[str, Command] = {
    "router": Command("services.router:RouterSettings", "services.router:run", "run a Zenoh router"),
    "sim": Command(
        "sim_service.responder:SimSettings",
        "sim_service.responder:run",
        "serve the MuJoCo world",
        check="sim_service.responder:check",
    ),
    "encoder": Command(
        "encoder_service.service:EncoderSettings", "encoder_service.service:run", "serve the CMVAE: obs -> latent"
    ),
    "learn": Command(
        "learner_service.command:LearnCommandSettings",
        "learner_service.command:run",
        "train a learner",
        check="learner_service.command:check",
        renders=True,
    ),
    "eval": Command(
        "eval_service.command:EvalCommandSettings",
        "eval_service.command:run",
        "evaluate checkpoints",
        check="eval_service.command:check",
        renders=True,
    ),
    "dataset": Command("sim_service.dataset:DatasetSettings", "sim_service.dataset:run", "write a CMVAE dataset"),
    "train-encoder": Command(
        "encoder_service.train:TrainEncoderSettings", "encoder_service.train:run", "train the CMVAE"
    ),
    "eval-encoder": Command(
        "encoder_service.evaluate:EvalEncoderSettings", "encoder_service.evaluate:run", "evaluate a CMVAE"
    ),
    "export-encoder": Command(
        "encoder_service.export:ExportEncoderSettings", "encoder_service.export:run", "shrink a CMVAE for shipping"
    ),
    "export": Command(
        "learner_service.export:ExportSettings",
        "learner_service.export:run",
        "a policy as one ONNX file, frame to action",
        renders=True,
    ),
    "up": Command(
        "learner_service.up:UpSettings",
        "learner_service.up:run",
        "launch router, sim, encoder, learner (shipped recipe)",
        default_config="learner_service/models/sac_cmvae_general.yaml",
        check="learner_service.up:check",
    ),
    "status": Command(
        "services.status:StatusSettings",
        "services.status:run",
        "who is live in a namespace, and doing what",
        check="services.status:check",
        answers=True,
    ),
    "pilot": Command(
        "pilot_service.pilot:PilotSettings", "pilot_service.pilot:run", "fly ArduSub from a video stream (ONNX policy)"
    ),
    "record": Command(
        "services.record:RecordSettings", "services.record:run_record", "record every key of a namespace to MCAP"
    ),
    "replay": Command(
        "services.record:ReplaySettings", "services.record:run_replay", "publish an MCAP recording back into its keys"
    ),
    "bench": Command(
        "bench.command:BenchSettings",
        "bench.command:run",
        "run a benchmark: sim | encoder | train | learn",
        renders=True,
    ),
}


def _resolve(path: str) -> Any:
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


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
            settings_mod.add_arguments(command_parser, _resolve(spec.settings), recipe(name))
    return parser


def recipe(command: str) -> Path | None:
    """The settings file a command reads when no ``--config`` is given, or None."""
    default = COMMANDS[command].default_config
    return Path(__file__).resolve().parents[1] / default if default else None  # package data beside services/


def config_file(command: str, given: str | None) -> str | None:
    """The settings file of a run: ``--config`` if given, else the command's default (logged), else none."""
    default = recipe(command)
    if given or default is None:
        return given
    log.info("settings from %s (--config FILE replaces them; flags and SWIMM_* still override)",
             COMMANDS[command].default_config)  # fmt: skip
    return str(default)


def checked_settings(command: str, argv: list[str], environ: dict[str, str] | None = None) -> Any:
    """The settings ``swimm <command> <argv>`` would run with, refused (:class:`SettingsError`) as that command
    would refuse them: `swimm up` checks every process it will start this way before it starts any."""
    spec = COMMANDS[command]
    args = build_parser(command).parse_args([command, *argv])
    settings = settings_mod.load(_resolve(spec.settings), args, config_file(command, args.config), environ)
    if spec.check:
        try:
            _resolve(spec.check)(settings)
        except (ValueError, FileNotFoundError) as exc:
            raise settings_mod.SettingsError(str(exc)) from None
    return settings


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    command = next((a for a in argv if not a.startswith("-")), None)
    parser = build_parser(command if command in COMMANDS else None)
    args = parser.parse_args(argv)
    spec = COMMANDS[args.command]
    setup_logging(args.command, args.log_level)
    stop_when_launcher_exits()
    try:
        settings = settings_mod.load(_resolve(spec.settings), args, config_file(args.command, args.config))
        if spec.check:
            _resolve(spec.check)(settings)
        # Process-wide settings (switch interval, ZENOH_RUNTIME, LP_NUM_THREADS): here, once, never in library code.
        level = logging.DEBUG if spec.answers else logging.INFO
        configure_process(ProcessSettings.of(settings, renders=spec.renders), role=args.command, level=level)
    except (ValueError, FileNotFoundError) as exc:  # the user's to change: said once, and never retried
        log.error("%s refused its settings: %s", args.command, exc)
        return settings_mod.SETTINGS_EXIT_CODE
    try:
        result = _resolve(spec.run)(settings)
    except KeyboardInterrupt:
        return 130
    except Exception as exc:  # the CLI's last line of defence: a clear message, not a traceback
        if logging.getLogger().isEnabledFor(logging.DEBUG):
            raise
        log.error("%s failed: %s", args.command, exc)
        return 1
    return int(result) if isinstance(result, int) else 0


if __name__ == "__main__":
    sys.exit(main())
