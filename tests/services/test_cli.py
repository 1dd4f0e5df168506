"""The `swimm` command line, run as users run it: in its own process."""

from __future__ import annotations

import dataclasses
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from services.procs import wait_for_port
from services.record import McapRecorder
from swimm.cli import COMMANDS

#: The command line DESIGN.md promises.
DESIGNED_COMMANDS = ("router", "sim", "encoder", "learn", "eval", "dataset", "train-encoder", "up", "bench")


def swimm(*args: str, timeout_s: float = 30.0, env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """Run ``python -m swimm <args>`` to completion and capture its output."""
    return subprocess.run(
        [sys.executable, "-m", "swimm", *args], capture_output=True, text=True, timeout=timeout_s, env=env
    )


def test_help_lists_every_command_with_its_summary():
    result = swimm("--help")
    assert result.returncode == 0
    assert set(DESIGNED_COMMANDS) <= set(COMMANDS)
    for name, command in COMMANDS.items():
        assert name in result.stdout
        assert command.help in result.stdout


def test_a_sub_commands_help_lists_its_settings_as_flags_with_defaults_and_variables():
    result = swimm("router", "--help")
    assert result.returncode == 0
    shown = " ".join(result.stdout.split())  # argparse wraps help lines
    for text in (
        "--listen",
        "--connect",
        "--zenoh-config",
        "--config CONFIG",
        "--log-level",
        "endpoints to listen on; none: the --zenoh-config file's, else tcp/127.0.0.1:7447",
        "(default: []; env SWIMM_LISTEN)",
        "e.g. deploy/zenoh/router-tls-acl.json5 (default: None; env SWIMM_ZENOH_CONFIG)",
    ):
        assert text in shown


@pytest.mark.parametrize(
    ("argv", "heavy"), [(["--help"], ("torch", "mujoco")), (["router", "--help"], ("torch", "mujoco")),
                        (["sim", "--help"], ("torch",))],
)  # fmt: skip
def test_help_imports_no_heavy_package_the_command_does_not_need(argv: list[str], heavy: tuple[str, ...]) -> None:
    probe = (
        "import sys\n"
        "from swimm import cli\n"
        "try:\n"
        f"    cli.main({argv!r})\n"
        "except SystemExit:\n"
        "    pass\n"
        f"print(sorted(m for m in {heavy!r} if m in sys.modules))\n"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip().splitlines()[-1] == "[]"


@pytest.mark.parametrize("name", COMMANDS)
def test_every_command_loads_its_settings_check_and_run_function(name: str) -> None:
    entry = COMMANDS[name].load()
    assert dataclasses.is_dataclass(entry.settings) and callable(entry.run)
    assert callable(entry.check) or name == "router"  # the router reads no file and has nothing to refuse


@pytest.mark.parametrize(
    ("argv", "refusal"),
    [
        (["train-encoder", "--dataset", "NOWHERE"], "NOWHERE is not a CMVAE dataset"),
        (["train-encoder", "--dataset", "NOWHERE", "--mask-weight", "-1"], "--mask-weight must be a finite weight"),
        (["train-encoder", "--dataset", "DATASET", "--init", "NOT_A_MODEL"], "--init NOT_A_MODEL is not a swimm-cmvae"),
        (["eval-encoder", "--dataset", "NOWHERE"], "NOWHERE is not a CMVAE dataset"),
        (["export-encoder", "--checkpoint", "NOT_A_MODEL"], "NOT_A_MODEL is not a swimm-cmvae checkpoint"),
        (["export", "--checkpoint", "NOT_A_MODEL"], "NOT_A_MODEL is not a policy checkpoint"),
        (["export", "--check-frames", "0"], "--check-frames 0: must be >= 1"),
        (["encoder", "--checkpoint", "NOT_A_MODEL"], "NOT_A_MODEL is not a swimm-cmvae checkpoint"),
        (["encoder", "--device", "banana"], "--device 'banana' is not a torch device"),
        (["train-encoder", "--dataset", "NOWHERE", "--device", "banana"], "--device 'banana' is not a torch device"),
        (
            ["encoder", "--device", "cuda", "--engine", "onnx"],
            "encoder engine must be one of torch, onnx (onnx on the cpu device only), got 'onnx' on 'cuda'",
        ),
        (["pilot", "--policy", "NOT_A_MODEL"], "NOT_A_MODEL"),
        (["pilot", "--max-surge", "2"], "--max-surge, --max-yaw and --max-heave must be in (0, 1]"),
        (["record", "--duration-s", "-1"], "--duration-s must be >= 0"),
        (["sim", "--train-envs", "0", "--eval-envs", "0"], "--train-envs 0 and --eval-envs 0: the sim would serve no"),
        (["replay", "NOT_A_MODEL"], "NOT_A_MODEL is not a readable MCAP recording"),
        (["eval", "--recording", "NOT_A_MODEL"], "NOT_A_MODEL is not a readable MCAP recording"),
        (["eval", "--watch", "NOWHERE"], "--watch NOWHERE: nothing to watch"),
        (["bench", "learn", "--algos", "nonesuch"], "unknown algorithm 'nonesuch'"),
        (["replay", "RECORDING", "--keys", "a//b"], "--keys 'a//b' is not a key expression: Invalid Key Expr"),
        (["dataset", "--out", "DATASET", "--count", "5"], "--out DATASET already holds a dataset (meta.json)"),
        (["dataset", "--count", "5", "--noise-preset", "muddy"], "unknown noise preset 'muddy'"),
    ],
)
def test_each_command_refuses_bad_input_by_name_before_it_starts(argv, refusal, tmp_path, capfd) -> None:
    """Exit 2, "<command> refused its settings: ...", and nothing written: the files the command would read or
    write are checked before any model loads, any frame renders or any session opens."""
    from swimm import cli

    not_a_model = tmp_path / "notes.txt"
    not_a_model.write_text("not a model")
    dataset = tmp_path / "dataset"
    dataset.mkdir()
    (dataset / "meta.json").write_text("{}")  # a folder that claims a dataset
    recording = tmp_path / "session.mcap"
    McapRecorder(recording, "swimm/default", images=False).close()  # an empty recording, as `swimm record` writes
    names = {"NOWHERE": tmp_path / "nowhere", "NOT_A_MODEL": not_a_model, "DATASET": dataset, "RECORDING": recording}
    argv = [str(names.get(arg, arg)) for arg in argv]
    refusal = next((refusal.replace(key, str(path)) for key, path in names.items() if key in refusal), refusal)
    before = sorted(tmp_path.rglob("*"))
    assert cli.main(argv) == 2
    assert f"{argv[0]} refused its settings: {refusal}" in capfd.readouterr().err
    assert sorted(tmp_path.rglob("*")) == before


def test_console_script_is_installed():
    """The environment's own `swimm` (install.sh links a launcher on PATH to it)."""
    executable = Path(sys.executable).with_name("swimm")
    assert executable.is_file(), "run ./install.sh (as .ci/run does) to install the swimm command"
    result = subprocess.run([executable, "--help"], capture_output=True, text=True, timeout=30)
    assert result.returncode == 0
    assert "router" in result.stdout


@pytest.mark.parametrize(
    ("args", "error"),
    [
        ((), "the following arguments are required: COMMAND"),
        (("fly",), "argument COMMAND: invalid choice: 'fly'"),
        (("router", "--port", "7447"), "unrecognized arguments: --port 7447"),
    ],
)
def test_usage_errors_exit_2_with_the_reason(args, error):
    result = swimm(*args)
    assert result.returncode == 2
    assert error in result.stderr


def test_a_refused_setting_exits_2_with_one_clear_line_not_a_traceback(tmp_path):
    result = swimm("router", "--config", str(tmp_path / "absent.yaml"))
    assert result.returncode == 2  # a settings error: `swimm up` never restarts a process that exits so
    assert f"router refused its settings: --config {tmp_path / 'absent.yaml'}: No such file" in result.stderr
    assert "Traceback" not in result.stderr


def test_router_listens_where_the_variable_says_and_drains_on_sigterm(spawn, processes, free_port):
    port = free_port()
    processes.env["SWIMM_LISTEN"] = f"tcp/127.0.0.1:{port}"
    router = spawn("router")
    assert wait_for_port("127.0.0.1", port, timeout_s=20), router.log_tail()
    router.process.send_signal(signal.SIGTERM)
    assert router.process.wait(timeout=10) == 0
    log = router.log_tail()
    assert f"listen=tcp/127.0.0.1:{port}" in log
    assert "router stopped" in log


def test_flags_override_the_yaml_file(spawn, free_port, tmp_path):
    file_port, flag_port = free_port(), free_port()
    config = tmp_path / "router.yaml"
    config.write_text(f"listen: [tcp/127.0.0.1:{file_port}]\n")
    router = spawn("router", "--config", str(config), "--listen", f"tcp/127.0.0.1:{flag_port}")
    assert wait_for_port("127.0.0.1", flag_port, timeout_s=20), router.log_tail()
    assert not wait_for_port("127.0.0.1", file_port, timeout_s=0.2)


def test_up_runs_the_shipped_recipe_unless_given_a_settings_file(tmp_path) -> None:
    from learner_service.up import UpSettings
    from services import settings as settings_mod
    from swimm.cli import build_parser, config_file

    def up_settings(*argv: str) -> UpSettings:
        args = build_parser("up").parse_args(["up", *argv])
        return settings_mod.load(UpSettings, args, config_file("up", args.config), environ={})

    recipe = up_settings()
    assert recipe.learn.demo.steps == 24000 and recipe.learn.steps == 20000  # sac_cmvae_wide.yaml
    assert up_settings("--seed", "101").learn.seed == 101  # flags still override the recipe
    spec = up_settings("--config", "learner_service/configs/sac_spec.yaml")
    assert spec.learn.demo.steps == 0 and spec.learn.steps == 1_000_000 and spec.learn.hyperparams == ""
    assert config_file("sim", None) is None


def test_up_help_shows_the_values_a_plain_run_uses() -> None:
    """The recipe a plain `swimm up` reads replaces some defaults; --help shows its values and names it."""
    shown = " ".join(swimm("up", "--help").stdout.split())
    assert "A plain run reads the recipe learner_service/models/sac_cmvae_wide.yaml" in shown
    assert "(default: 20000 from sac_cmvae_wide.yaml; env SWIMM_STEPS)" in shown
    assert "(default: 24000 from sac_cmvae_wide.yaml; env SWIMM_DEMO_STEPS)" in shown
    assert "(default: 1 from sac_cmvae_wide.yaml; env SWIMM_EVAL_MIN_STEPS)" in shown
    assert "(default: 7447; env SWIMM_PORT)" in shown  # not in the recipe: the field's own


def test_a_client_logs_the_endpoints_it_uses_not_the_routers_stock_listener(spawn, processes, free_port) -> None:
    port = free_port()
    endpoint = processes.start_router(port)
    status = spawn("status", "--connect", endpoint, "--log-level", "DEBUG", "--window-s", "0.2")
    status.process.wait(timeout=30)
    joined = next(line for line in status.log_tail(200).splitlines() if "joined Zenoh" in line)
    assert f"connect={endpoint} listen=none" in joined and "7447" not in joined
