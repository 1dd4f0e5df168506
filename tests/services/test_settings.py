"""Settings layering: defaults < YAML file < SWIMM_* environment < command-line flags, for nested and flat fields."""

from __future__ import annotations

import argparse
import dataclasses
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from services import settings as settings_mod
from services.settings import ZenohSettings


@dataclasses.dataclass
class Noise:
    fog: float = 0.0  # density of the fog
    blur: bool = False


@dataclasses.dataclass
class Example:
    """A command's settings with every kind of field the loader supports."""

    steps: int = 100
    render: bool = True
    algo: str = "sac"
    checkpoint: str | None = None
    seeds: list[int] = dataclasses.field(default_factory=lambda: [1, 2])
    image_shape: tuple[int, int, int] = (64, 64, 3)
    noise: Noise = dataclasses.field(default_factory=Noise)
    zenoh: ZenohSettings = dataclasses.field(default_factory=ZenohSettings, metadata={"flatten": True})
    target: str = dataclasses.field(default="sim", metadata={"positional": True})


def _parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    settings_mod.add_arguments(parser, Example)
    return parser.parse_args(list(argv))


def _load(*argv: str, environ: dict[str, str] | None = None, config_file=None) -> Example:
    return settings_mod.load(Example, _parse(*argv), config_file, environ or {})


def test_defaults_hold_when_nothing_is_given():
    loaded = _load()
    assert loaded == Example()
    assert loaded.zenoh.connect == []  # open_session then uses the config file's endpoints, else LOCAL_ROUTER
    assert loaded.zenoh.startup_timeout_s == 60.0


def test_each_layer_overrides_the_one_below(tmp_path):
    config = tmp_path / "run.yaml"
    config.write_text("steps: 200\nalgo: ppo\nnoise:\n  fog: 0.2\nconnect: [tcp/10.0.0.1:7447]\n")
    environ = {"SWIMM_ALGO": "td3", "SWIMM_NOISE_FOG": "0.4"}

    from_file = _load(config_file=config)
    assert (from_file.steps, from_file.algo, from_file.noise.fog) == (200, "ppo", 0.2)
    assert from_file.zenoh.connect == ["tcp/10.0.0.1:7447"]

    from_env = _load(config_file=config, environ=environ)
    assert (from_env.steps, from_env.algo, from_env.noise.fog) == (200, "td3", 0.4)

    from_flags = _load("--noise-fog", "0.6", "--steps", "300", config_file=config, environ=environ)
    assert (from_flags.steps, from_flags.algo, from_flags.noise.fog) == (300, "td3", 0.6)
    assert from_flags.zenoh.connect == ["tcp/10.0.0.1:7447"]  # untouched by higher layers


def test_nested_fields_are_prefixed_and_flattened_fields_keep_their_names():
    parser = argparse.ArgumentParser()
    settings_mod.add_arguments(parser, Example)
    flags = set(re.findall(r"--[a-z][a-z0-9-]*", parser.format_help()))
    assert {"--noise-fog", "--noise-blur", "--no-noise-blur", "--steps", "--image-shape"} <= flags
    assert {"--connect", "--listen", "--namespace", "--startup-timeout-s", "--zenoh-config"} <= flags
    assert {flag for flag in flags if flag.startswith("--zenoh-")} == {"--zenoh-config", "--zenoh-threads"}

    loaded = _load(environ={"SWIMM_NOISE_BLUR": "true", "SWIMM_NAMESPACE": "swimm/lab", "SWIMM_MODE": "peer"})
    assert loaded.noise.blur is True
    assert (loaded.zenoh.namespace, loaded.zenoh.mode) == ("swimm/lab", "peer")


@dataclasses.dataclass
class Switched:
    """A mode switch beside its settings group, whose flags share the switch's name (``--sweep-preset``)."""

    sweep: bool = False
    sweep_plan: Noise = dataclasses.field(default_factory=Noise, metadata={"stem": "sweep"})


def test_a_group_with_a_stem_takes_its_flags_names_from_the_stem(tmp_path):
    parser = argparse.ArgumentParser()
    settings_mod.add_arguments(parser, Switched)
    flags = set(re.findall(r"--[a-z][a-z0-9-]*", parser.format_help()))
    assert {"--sweep", "--sweep-fog", "--sweep-blur"} <= flags
    assert not any(flag.startswith("--sweep-plan") for flag in flags)
    loaded = settings_mod.load(Switched, parser.parse_args(["--sweep", "--sweep-fog", "0.5"]), None, {})
    assert (loaded.sweep, loaded.sweep_plan.fog) == (True, 0.5)
    flat, nested = tmp_path / "flat.yaml", tmp_path / "nested.yaml"
    flat.write_text("sweep_blur: true\n")
    nested.write_text("sweep_plan: {blur: true}\n")
    for config in (flat, nested):
        assert settings_mod.load(Switched, None, config, {"SWIMM_SWEEP_FOG": "0.25"}).sweep_plan == Noise(0.25, True)


def test_yaml_accepts_nested_maps_and_flat_names(tmp_path):
    nested = tmp_path / "nested.yaml"
    nested.write_text("noise: {fog: 0.3, blur: true}\nzenoh: {namespace: swimm/a}\n")
    flat = tmp_path / "flat.yaml"
    flat.write_text("noise_fog: 0.3\nnoise_blur: true\nnamespace: swimm/a\n")
    for config in (nested, flat):
        loaded = _load(config_file=config)
        assert (loaded.noise.fog, loaded.noise.blur, loaded.zenoh.namespace) == (0.3, True, "swimm/a")


def test_an_empty_yaml_file_means_defaults(tmp_path):
    config = tmp_path / "empty.yaml"
    config.write_text("")
    assert _load(config_file=config) == Example()


def test_lists_parse_from_comma_separated_variables_and_repeated_flag_values():
    from_env = _load(environ={"SWIMM_CONNECT": "tcp/a:1, tcp/b:2,", "SWIMM_SEEDS": "3,5,8"})
    assert from_env.zenoh.connect == ["tcp/a:1", "tcp/b:2"]
    assert from_env.seeds == [3, 5, 8]

    from_flags = _load("--connect", "tcp/c:3", "tcp/d:4", "--seeds", "13", "21", "--image-shape", "32", "32", "3")
    assert from_flags.zenoh.connect == ["tcp/c:3", "tcp/d:4"]
    assert from_flags.seeds == [13, 21]
    assert from_flags.image_shape == (32, 32, 3)  # a tuple field stays a tuple


def test_empty_list_flag_clears_the_default():
    assert _load("--connect").zenoh.connect == []


@pytest.mark.parametrize(
    ("text", "expected"),
    [("1", True), ("true", True), ("YES", True), ("on", True), ("0", False), ("False", False), ("no", False)],
)
def test_booleans_parse_from_variables(text, expected):
    assert _load(environ={"SWIMM_RENDER": text}).render is expected


def test_boolean_flags_have_a_negative_form():
    assert _load("--no-render").render is False
    assert _load("--render", environ={"SWIMM_RENDER": "false"}).render is True


def test_optional_fields_accept_none_from_variables():
    assert _load(environ={"SWIMM_CHECKPOINT": "runs/a/best.zip"}).checkpoint == "runs/a/best.zip"
    assert _load(environ={"SWIMM_CHECKPOINT": "none"}).checkpoint is None


def test_help_describes_flags_by_their_field_comment_or_help_metadata():
    parser = argparse.ArgumentParser()
    settings_mod.add_arguments(parser, Example)
    helps = {action.dest: action.help for action in parser._actions}
    assert helps["noise_fog"] == "density of the fog (default: 0.0; env SWIMM_NOISE_FOG)"  # nested class's comment
    assert helps["noise_blur"] == "(default: False; env SWIMM_NOISE_BLUR)"  # no comment: the default alone
    assert helps["connect"].startswith("endpoints to connect to;")  # metadata wins where a field spans lines
    assert helps["zenoh_config"].startswith("a Zenoh JSON5 config file;")


def test_positional_field_is_an_optional_argument():
    assert _load().target == "sim"
    assert _load("encoder").target == "encoder"
    assert _load(environ={"SWIMM_TARGET": "train"}).target == "train"


@pytest.mark.parametrize(
    ("name", "text", "reason"),
    [
        ("SWIMM_RENDER", "maybe", "SWIMM_RENDER: 'maybe' is not a boolean"),
        ("SWIMM_STEPS", "many", "SWIMM_STEPS: invalid literal for int"),
        ("SWIMM_NOISE_FOG", "thick", "SWIMM_NOISE_FOG: could not convert"),
        ("SWIMM_SEEDS", "1,two", "SWIMM_SEEDS: invalid literal for int"),
    ],
)
def test_bad_variable_values_are_refused_naming_the_variable(name, text, reason):
    with pytest.raises(ValueError, match=reason):
        _load(environ={name: text})


def test_bad_flag_values_are_refused_by_the_parser(capsys):
    with pytest.raises(SystemExit) as exit_info:
        _parse("--steps", "many")
    assert exit_info.value.code == 2
    assert "--steps: invalid int value: 'many'" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("startup_timout_s: 5\n", r"unknown setting 'startup_timout_s'; did you mean startup_timeout_s\?"),
        ("noise:\n  fgo: 0.1\n", r"unknown setting 'noise.fgo'; did you mean fog\?"),
        ("low_latency: yes please\n", r"setting 'low_latency' got 'yes please': Input should be a valid boolean"),
        ("noise:\n  fog: thick\n", r"setting 'noise_fog' got 'thick': Input should be a valid number"),
        ("seeds: [1, two]\n", r"setting 'seeds' got \[1, 'two'\]: Input should be a valid integer"),
        ("image_shape: [64, 64]\n", r"setting 'image_shape'.*Field required"),
    ],
)
def test_a_yaml_mistake_is_refused_naming_the_file_and_the_setting(tmp_path, text, reason):
    config = tmp_path / "bad.yaml"
    config.write_text(text)
    with pytest.raises(ValueError, match=f"settings file {re.escape(str(config))}: {reason}"):
        _load(config_file=config)


def test_yaml_values_are_coerced_as_their_fields_type_says(tmp_path):
    config = tmp_path / "ok.yaml"
    config.write_text("steps: '250'\nnoise: {fog: 1}\nseeds: 7\nimage_shape: [32, 32, 3]\nzenoh: {namespace: a/b}\n")
    loaded = _load(config_file=config)
    assert loaded.steps == 250 and loaded.noise.fog == 1.0 and isinstance(loaded.noise.fog, float)
    assert loaded.seeds == [7] and loaded.image_shape == (32, 32, 3) and loaded.zenoh.namespace == "a/b"


def test_a_yaml_file_that_is_not_a_mapping_is_refused(tmp_path):
    config = tmp_path / "list.yaml"
    config.write_text("- steps\n- 200\n")
    with pytest.raises(ValueError, match="must hold a YAML mapping"):
        _load(config_file=config)


def test_process_environment_is_read_when_no_mapping_is_given(monkeypatch):
    # monkeypatch.setenv only scopes a real environment variable to this test; nothing is faked.
    monkeypatch.setenv("SWIMM_STEPS", "7")
    assert settings_mod.load(Example).steps == 7


def test_to_dict_is_plain_nested_data():
    view = settings_mod.to_dict(_load("--noise-fog", "0.5"))
    assert view["noise"] == {"fog": 0.5, "blur": False}
    assert view["zenoh"]["connect"] == []
    assert view["steps"] == 100


def test_every_shipped_settings_file_passes_validation():
    from pathlib import Path

    from learner_service.up import UpSettings
    from sim_service.settings import SimSettings

    root = Path(__file__).resolve().parents[2]
    shipped = {UpSettings: [*root.glob("learner_service/models/*.yaml"), *root.glob("learner_service/configs/*.yaml")],
               SimSettings: list(root.glob("sim_service/configs/*.yaml"))}  # fmt: skip
    for cls, files in shipped.items():
        assert files
        for path in files:
            settings_mod.load(cls, None, path, {})  # raises, naming the file and the key, on any mistake


def test_a_choice_is_checked_in_one_place_whichever_layer_gives_it(tmp_path, capsys):
    """ZenohSettings.mode is a Literal: flags, variables and YAML all refuse what it does not list."""
    assert _load("--mode", "peer").zenoh.mode == "peer"
    with pytest.raises(SystemExit):
        _parse("--mode", "mesh")
    assert "invalid choice: 'mesh' (choose from 'client', 'peer', 'router')" in capsys.readouterr().err
    with pytest.raises(ValueError, match="SWIMM_MODE: setting 'mode' got 'mesh': Input should be 'client', 'peer'"):
        _load(environ={"SWIMM_MODE": "mesh"})
    config = tmp_path / "mode.yaml"
    config.write_text("mode: mesh\n")
    with pytest.raises(ValueError, match="setting 'mode' got 'mesh'"):
        _load(config_file=config)


@pytest.mark.parametrize(
    ("values", "reason"),
    [
        ({"fogg": 1.0}, "noise: unknown setting 'fogg'; did you mean fog"),
        ({"fog": "0.1"}, "setting 'fog' got '0.1': Input should be a valid number"),  # no text for a number
        ({"fog": True}, "setting 'fog' got True"),  # nor a bool
        ({"jpeg_quality": 30.0}, "setting 'jpeg_quality' got 30.0: Input should be a valid integer"),
        ({"attenuation_rgb": 1.0}, "setting 'attenuation_rgb' got 1.0"),  # no item where a list goes
        ({"attenuation_rgb": [1.0, float("inf"), 0.3]}, "a finite number is needed"),
        ({"fog": float("nan")}, "a finite number is needed"),
    ],
)
def test_a_messages_settings_are_checked_strictly_by_name(values, reason) -> None:
    from sim_service.noise import NoiseSettings

    with pytest.raises(ValueError, match=re.escape(reason)):
        settings_mod.from_message(NoiseSettings, values, "noise")


def test_a_messages_settings_keep_the_defaults_they_leave_out() -> None:
    from sim_service.latency import LatencySettings

    got = settings_mod.from_message(LatencySettings, {"action_delay": 4, "randomise": True}, "latency")
    assert got == LatencySettings(action_delay=4, randomise=True)


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [
        ("render_scale", 0, "--render-scale 0: must be >= 1"),
        ("image_size", 0, "--image-size 0: must be >= 1"),
        ("physics_dt", 0.0, "--physics-dt 0.0: must be > 0"),
        ("render_threads", -2, "--render-threads -2: must be >= -1"),
    ],
)
def test_a_world_no_sim_can_render_is_refused_by_its_flag_in_a_file_and_in_code(tmp_path, field, value, reason):
    from sim_service.responder import check
    from sim_service.settings import SimSettings, WorldSettings

    config = tmp_path / "world.yaml"
    config.write_text(f"{field}: {value}\n")
    with pytest.raises(ValueError, match=f"setting '{field}' got {value}"):
        settings_mod.load(SimSettings, None, str(config), environ={})
    with pytest.raises(ValueError, match=reason):
        check(SimSettings(world=WorldSettings(**{field: value})))


def test_a_file_a_setting_names_is_read_here_or_else_from_swimms_own_files(tmp_path):
    """Run from another folder, a recipe and the repo-relative paths in it name swimm's shipped files; a file of
    that name in the current folder is taken first."""
    reader = (
        "from learner_service.learn_settings import LearnCommandSettings\n"
        "from services.settings import from_command_line\n"
        "recipe = 'learner_service/models/sac_cmvae_wide.yaml'\n"
        "settings = from_command_line(LearnCommandSettings, ['--config', recipe])\n"
        "print(settings.encoder_checkpoint); print(settings.sim_config)\n"
    )
    root = Path(settings_mod.__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    shipped = subprocess.run([sys.executable, "-c", reader], cwd=tmp_path, env=env, capture_output=True, text=True,
                             timeout=120, check=True).stdout.split()  # fmt: skip
    assert shipped == [str(root / "encoder_service/models/cmvae_wide.pt"),
                       str(root / "sim_service/configs/randomised_noise_latency.yaml")]  # fmt: skip
    (tmp_path / "encoder_service/models").mkdir(parents=True)
    (tmp_path / "encoder_service/models/cmvae_wide.pt").write_bytes(b"mine")
    local = subprocess.run([sys.executable, "-c", reader], cwd=tmp_path, env=env, capture_output=True, text=True,
                           timeout=120, check=True).stdout.split()  # fmt: skip
    assert local == ["encoder_service/models/cmvae_wide.pt", shipped[1]]


def test_a_yaml_section_may_be_keyed_as_its_flags_are_below_a_flattened_group(tmp_path):
    """SimSettings flattens its world: ``--noise-preset`` is ``noise: {preset: ...}`` in YAML, as well as
    ``noise_preset`` and the attribute path ``world: {noise: {preset: ...}}``; a misspelt key names the close one."""
    from sim_service.settings import SimSettings

    for text in ("noise_preset: murky\n", "noise:\n  preset: murky\n", "world:\n  noise:\n    preset: murky\n"):
        config = tmp_path / "sim.yaml"
        config.write_text(text)
        assert settings_mod.load(SimSettings, None, config, {}).world.noise.preset == "murky", text
    config.write_text("noise:\n  presett: murky\n")
    with pytest.raises(settings_mod.SettingsError, match=r"unknown setting 'noise.presett'; did you mean preset\?"):
        settings_mod.load(SimSettings, None, config, {})
