"""Every `swimm` command: its summary, and a loader that imports its settings, check and run function.

Each loader imports its command's module inside itself, so ``swimm sim`` never imports torch and ``swimm --help``
imports neither torch nor MuJoCo (startup cost), while the import check still sees each command's imports: it
reads imports inside functions too.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Entry:
    settings: type  # the settings dataclass
    run: Callable[[Any], Any]  # takes the settings; an int it returns is the exit status
    check: Callable[[Any], Any] | None = None  # refuses bad settings before the command starts anything (exit 2)


@dataclass(frozen=True)
class Command:
    load: Callable[[], Entry]  # imports the command's module: only the chosen command's is imported
    help: str
    default_config: str = ""  # a settings file beside the packages, read when no --config is given
    renders: bool = False  # may render a World whose settings are not its own (in-process envs): LP_NUM_THREADS
    answers: bool = False  # its output is its answer: the process settings' line only at DEBUG


def _router() -> Entry:
    from services.router import RouterSettings
    from swimm.router import run

    return Entry(RouterSettings, run)


def _sim() -> Entry:
    from sim_service.responder import check, run
    from sim_service.settings import SimSettings

    return Entry(SimSettings, run, check)


def _encoder() -> Entry:
    from encoder_service.service import EncoderSettings, check, run

    return Entry(EncoderSettings, run, check)


def _learn() -> Entry:
    from learner_service.command import LearnCommandSettings, check_new_run, run

    return Entry(LearnCommandSettings, run, check_new_run)


def _eval() -> Entry:
    from eval_service.command import EvalCommandSettings, check, run

    return Entry(EvalCommandSettings, run, check)


def _dataset() -> Entry:
    from sim_service.dataset import DatasetSettings, check, run

    return Entry(DatasetSettings, run, check)


def _train_encoder() -> Entry:
    from encoder_service.train import TrainEncoderSettings, check, run

    return Entry(TrainEncoderSettings, run, check)


def _train_detector() -> Entry:
    from encoder_service.pod_detector_train import TrainDetectorSettings, check, run

    return Entry(TrainDetectorSettings, run, check)


def _eval_encoder() -> Entry:
    from encoder_service.evaluate import EvalEncoderSettings, check, run

    return Entry(EvalEncoderSettings, run, check)


def _export_encoder() -> Entry:
    from encoder_service.export import ExportEncoderSettings, check, run

    return Entry(ExportEncoderSettings, run, check)


def _export() -> Entry:
    from learner_service.export import ExportSettings, check, run

    return Entry(ExportSettings, run, check)


def _rebind() -> Entry:
    from learner_service.rebind import RebindSettings, check, run

    return Entry(RebindSettings, run, check)


def _up() -> Entry:
    from learner_service.up import UpSettings, check, run

    return Entry(UpSettings, run, check)


def _status() -> Entry:
    from swimm.status import StatusSettings, check, run

    return Entry(StatusSettings, run, check)


def _pilot() -> Entry:
    from pilot_service.pilot import PilotSettings, check, run

    return Entry(PilotSettings, run, check)


def _record() -> Entry:
    from services.record import RecordSettings
    from swimm.record import run_record

    return Entry(RecordSettings, run_record, RecordSettings.check)


def _replay() -> Entry:
    from services.record import ReplaySettings
    from swimm.record import run_replay

    return Entry(ReplaySettings, run_replay, ReplaySettings.check)


def _bench() -> Entry:
    from bench.command import BenchSettings, check, run

    return Entry(BenchSettings, run, check)


COMMANDS: dict[str, Command] = {
    "router": Command(_router, "run a Zenoh router"),
    "sim": Command(_sim, "serve the MuJoCo world"),
    "encoder": Command(_encoder, "serve the CMVAE: obs -> latent"),
    "learn": Command(_learn, "train a learner", renders=True),
    "eval": Command(_eval, "evaluate checkpoints", renders=True),
    "dataset": Command(_dataset, "write a CMVAE dataset"),
    "train-encoder": Command(_train_encoder, "train the CMVAE"),
    "train-detector": Command(_train_detector, "train the pod detector that finds every dolphin in a frame"),
    "eval-encoder": Command(_eval_encoder, "evaluate a CMVAE"),
    "export-encoder": Command(_export_encoder, "shrink a CMVAE for shipping"),
    "export": Command(_export, "a policy as ONNX, frame to action (two files on a detector)", renders=True),
    "rebind": Command(_rebind, "copy a policy to fly on a fine-tune of its CMVAE"),
    "up": Command(
        _up,
        "launch router, sim, encoder, learner (shipped recipe)",
        default_config="learner_service/models/sac_cmvae_wide.yaml",
    ),
    "status": Command(_status, "who is live in a namespace, and doing what", answers=True),
    "pilot": Command(_pilot, "fly ArduSub from a video stream (ONNX policy)"),
    "record": Command(_record, "record every key of a namespace to MCAP"),
    "replay": Command(_replay, "publish an MCAP recording back into its keys"),
    "bench": Command(_bench, "run a benchmark: sim | encoder | train | learn", renders=True),
}
