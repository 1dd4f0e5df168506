"""Settings: one dataclass per command, filled from defaults < YAML file < environment < CLI flags.

Each service declares its settings as plain dataclasses; this module turns
any such dataclass into command-line flags and environment variables, so
the dataclass is the single source of truth for names, types and defaults.

Naming: field ``max_wait_ms`` is flag ``--max-wait-ms`` and variable
``SWIMM_MAX_WAIT_MS``. A nested dataclass field ``noise`` contributes
``--noise-fog`` / ``SWIMM_NOISE_FOG``, unless the field is marked
``metadata={"flatten": True}`` (used for the Zenoh settings every command
shares), in which case its fields keep their own names (``--connect``), or ``metadata={"stem": "sweep"}``, in
which case they take that stem instead of the field's name (a group ``sweep_plan`` of ``--sweep-preset``...).
A field marked ``metadata={"positional": True}`` is an optional positional
argument instead of a flag (``swimm bench sim``). ``--help`` describes a flag by
``metadata={"help": ...}`` or else by the comment at the end of the field's line, so the comment
that documents a field in the source is also what the user reads.
A YAML file (``--config FILE``) holds the same names, flat (``noise_preset: murky``) or as nested maps, keyed as
the flags are (``noise: {preset: murky}`` for ``--noise-preset``) or by the attributes' path.

Every value, whatever layer it comes from, is validated against its field's type by pydantic (lax mode: the
YAML ``5`` fills a float, the text ``"5"`` an int; ``"yes please"`` fills no bool), and a YAML key that names no
field is refused with the closest names: a misspelled setting never passes silently.
"""

from __future__ import annotations

import argparse
import dataclasses
import difflib
import functools
import inspect
import math
import os
import re
import types
import typing
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

import pydantic
import yaml

from services.results import REPO_ROOT

T = TypeVar("T")
ENV_PREFIX = "SWIMM_"
SETTINGS_EXIT_CODE = 2  # a command that refused its settings exits with this (as argparse does): never retry it
LOCAL_ROUTER = "tcp/127.0.0.1:7447"  # where clients connect and `swimm router` listens when nothing says otherwise


class SettingsError(ValueError):
    """A setting the user must change; the command refuses it before it starts anything."""


def at_least(minimum: float) -> pydantic.fields.FieldInfo:
    """The range of a field that must be >= ``minimum``: ``Annotated[int, at_least(0)]``."""
    return pydantic.Field(ge=minimum)


def above(bound: float) -> pydantic.fields.FieldInfo:
    """The range of a field that must be > ``bound``: ``Annotated[float, above(0)]``."""
    return pydantic.Field(gt=bound)


def at_most(maximum: float) -> pydantic.fields.FieldInfo:
    """The range of a field that must be <= ``maximum``: ``Annotated[int, at_least(0), at_most(65535)]``."""
    return pydantic.Field(le=maximum)


NonNegInt = Annotated[int, at_least(0)]
PosInt = Annotated[int, at_least(1)]
NonNegFloat = Annotated[float, at_least(0)]
PosFloat = Annotated[float, above(0)]


def here_or_shipped(path: str) -> str:
    """``path`` as given, unless it is relative, names nothing from the current folder and names one of swimm's own
    files (a recipe's ``encoder_service/models/cmvae_wide.pt``): then that file, so a command runs from any folder."""
    if path and not Path(path).is_absolute() and not Path(path).exists() and (REPO_ROOT / path).exists():
        return str(REPO_ROOT / path)
    return path


#: A file a setting names: read from the current folder, or else among swimm's shipped files (``here_or_shipped``).
FilePath = Annotated[str, pydantic.AfterValidator(here_or_shipped)]


def flag(name: str) -> str:
    """The command-line flag of a leaf's name: ``eval_min_steps`` is ``--eval-min-steps``."""
    return "--" + name.replace("_", "-")


@dataclasses.dataclass
class ZenohSettings:
    """How a service joins the Zenoh network; shared by every command."""

    mode: Literal["client", "peer", "router"] = "client"
    connect: list[str] = dataclasses.field(
        default_factory=list,
        metadata={"help": f"endpoints to connect to; none: the --zenoh-config file's, else {LOCAL_ROUTER}"},
    )
    listen: list[str] = dataclasses.field(default_factory=list)
    zenoh_config: str | None = None  # a Zenoh JSON5 config file; endpoints given as flags override its own
    namespace: str = "swimm/default"
    startup_timeout_s: NonNegFloat = 60.0  # how long to wait for the router or peers at start
    low_latency: bool = False  # lock-step Zenoh: low-latency transport (messages < 48 KB), no shared memory
    zenoh_threads: NonNegInt = 1  # Zenoh's worker threads of this process, one pool for all; 0: a pool per runtime


@dataclasses.dataclass(frozen=True)
class _Leaf:
    path: tuple[str, ...]  # attribute path from the root dataclass
    name: str  # flag/variable stem, e.g. "noise_fog"
    kind: Any  # resolved type hint
    default: Any
    sections: tuple[str, ...] = ()  # its nested YAML keys as its flag names them: ("noise", "fog")


def _leaves(cls: type, path: tuple[str, ...] = (), stem: str = "", sections: tuple[str, ...] = ()) -> list[_Leaf]:
    hints = typing.get_type_hints(cls, include_extras=True)  # extras: the Annotated ranges
    instance_defaults = cls()
    leaves: list[_Leaf] = []
    for f in dataclasses.fields(cls):
        kind = hints[f.name]
        name = f"{stem}{f.name}"
        if dataclasses.is_dataclass(kind):
            flatten = f.metadata.get("flatten")
            section = f.metadata.get("stem", f.name)
            sub_stem = stem if flatten else f"{stem}{section}_"
            leaves.extend(_leaves(kind, (*path, f.name), sub_stem, sections if flatten else (*sections, section)))
        else:
            default = getattr(instance_defaults, f.name)
            leaves.append(_Leaf((*path, f.name), name, kind, default, (*sections, f.name)))
    return leaves


def _base_type(kind: Any) -> tuple[Any, bool]:
    """(underlying type, optional?) for hints such as ``str | None`` or ``Annotated[int, at_least(0)]``."""
    if typing.get_origin(kind) is Annotated:
        kind = typing.get_args(kind)[0]
    origin = typing.get_origin(kind)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(kind) if a is not type(None)]
        return args[0], True
    return kind, False


def _parse_text(kind: Any, text: str) -> Any:
    """Convert an environment variable's text to the field's type."""
    base, optional = _base_type(kind)
    if optional and text.strip().lower() in ("", "none", "null"):
        return None
    origin = typing.get_origin(base)
    if origin in (list, tuple):
        (item,) = typing.get_args(base)[:1] or (str,)
        items = [_parse_text(item, part.strip()) for part in text.split(",") if part.strip()]
        return items if origin is list else tuple(items)
    if base is bool:
        if text.strip().lower() in ("1", "true", "yes", "on"):
            return True
        if text.strip().lower() in ("0", "false", "no", "off"):
            return False
        raise ValueError(f"{text!r} is not a boolean (use true/false)")
    if origin is Literal:
        return text  # checked against the choices by `validated`
    return base(text)


_FIELD_COMMENT = re.compile(r"^\s+(\w+)\s*:[^#]*#\s*(.+?)\s*$")


@functools.cache
def field_comments(cls: type) -> dict[str, str]:
    """The trailing ``# comment`` of each one-line field of a dataclass and the dataclasses it extends, by field
    name ({} without source)."""
    names = {f.name for f in dataclasses.fields(cls)}
    comments: dict[str, str] = {}
    for declaring in reversed(cls.__mro__):  # a subclass's comment on a field wins over its base's
        if not dataclasses.is_dataclass(declaring):
            continue
        try:
            source = inspect.getsource(declaring)
        except (OSError, TypeError):
            continue
        found = (_FIELD_COMMENT.match(line) for line in source.splitlines())
        comments |= {m.group(1): m.group(2) for m in found if m and m.group(1) in names}
    return comments


def _owner(cls: type, path: tuple[str, ...]) -> type:
    """The dataclass that declares the leaf at ``path``."""
    for attr in path[:-1]:
        cls = typing.get_type_hints(cls)[attr]
    return cls


def add_arguments(parser: argparse.ArgumentParser, cls: type, recipe: str | Path | None = None) -> None:
    """Add one flag per leaf field of ``cls``; unset flags stay None so lower layers show through.

    ``recipe``: the settings file a plain run reads; its values are shown as the defaults they replace, so
    ``--help`` shows what a plain run uses."""
    group = parser.add_argument_group(cls.__name__)
    tree = read_tree(recipe, cls) if recipe else {}
    for leaf in _leaves(cls):
        option = flag(leaf.name)
        base, _ = _base_type(leaf.kind)
        metadata = field_metadata(cls, leaf.path)
        found, value = _from_file(tree, leaf, cls)
        default = f"{value!r} from {Path(recipe).name}" if found else repr(leaf.default)
        help_text = f"(default: {default}; env {ENV_PREFIX}{leaf.name.upper()})"
        description = metadata.get("help") or field_comments(_owner(cls, leaf.path)).get(leaf.path[-1])
        if description:
            help_text = f"{description} {help_text}"
        choices = typing.get_args(base) if typing.get_origin(base) is Literal else None
        if choices:
            group.add_argument(option, dest=leaf.name, choices=choices, default=None, help=help_text)
        elif metadata.get("positional"):
            group.add_argument(leaf.name, nargs="?", type=base, default=None, help=help_text)
        elif base is bool:
            group.add_argument(
                option, dest=leaf.name, action=argparse.BooleanOptionalAction, default=None, help=help_text
            )
        elif typing.get_origin(base) in (list, tuple):
            (item,) = typing.get_args(base)[:1] or (str,)
            # extend: a repeated flag adds to the list (`--checkpoint a --checkpoint b`) instead of replacing it
            group.add_argument(
                option, dest=leaf.name, nargs="*", action="extend", type=item, default=None, help=help_text
            )
        else:
            group.add_argument(option, dest=leaf.name, type=base, default=None, help=help_text)


def field_metadata(cls: type, path: tuple[str, ...]) -> typing.Mapping[str, Any]:
    """The dataclass field metadata of a leaf (``flatten``, ``stem``, ``positional``, ``help``)."""
    return {f.name: f.metadata for f in dataclasses.fields(_owner(cls, path))}[path[-1]]


def _set(target: Any, path: tuple[str, ...], value: Any) -> None:
    for attr in path[:-1]:
        target = getattr(target, attr)
    setattr(target, path[-1], value)


def _from_file(tree: dict[str, Any], leaf: _Leaf, cls: type) -> tuple[bool, Any]:
    """Find a leaf in a YAML tree by its flat name, its nested attribute path or its nested flag sections."""
    if leaf.name in tree:
        return True, tree[leaf.name]
    for keys in (leaf.path, leaf.sections):
        node: Any = tree
        for key in keys:
            if not isinstance(node, dict) or key not in node:
                break
            node = node[key]
        else:
            return True, node
    return False, None


def check_keys(tree: dict[str, Any], cls: type, source: str) -> None:
    """Refuse a YAML key that names no field of ``cls`` (by flat name, nested path or flag sections), suggesting close
    names."""
    leaves = _leaves(cls)
    flat = {leaf.name for leaf in leaves}
    paths = {leaf.path for leaf in leaves} | {leaf.sections for leaf in leaves}
    sections = {keys[:end] for keys in paths for end in range(1, len(keys))}

    def walk(node: dict[str, Any], path: tuple[str, ...]) -> None:
        for key, value in node.items():
            here = (*path, str(key))
            if (not path and key in flat) or here in paths:
                continue
            if here in sections and isinstance(value, dict):
                walk(value, here)
                continue
            known = sorted(flat) if not path else sorted({keys[-1] for keys in paths if keys[:-1] == path})
            close = difflib.get_close_matches(str(key), known, n=3)
            hint = f"; did you mean {' or '.join(close)}?" if close else f"; known: {', '.join(known)}"
            raise SettingsError(f"{source}: unknown setting {'.'.join(here)!r}{hint}")

    walk(tree, ())


@functools.cache
def _adapter(kind: Any) -> pydantic.TypeAdapter:
    return pydantic.TypeAdapter(kind)


def validated(leaf: _Leaf, value: Any, source: str, strict: bool = False) -> Any:
    """``value`` as the leaf's type, or a ValueError naming the setting, where it came from, and what was wrong.

    ``strict``: no conversion at all (a message's typed values: no "3" for 3, no true for 1, no item for a list)."""
    base, _ = _base_type(leaf.kind)
    if not strict and typing.get_origin(base) is list and value is not None and not isinstance(value, list | tuple):
        value = [value]  # one item where a list goes: a YAML `dataset: folder` means [folder]
    try:
        return _adapter(leaf.kind).validate_python(value, strict=strict)
    except pydantic.ValidationError as exc:
        reasons = "; ".join(_reason(error) for error in exc.errors())
        if source.startswith("--"):  # a flag names the setting itself: "--steps -5: must be >= 0"
            raise SettingsError(f"{source} {value!r}: {reasons}") from None
        raise SettingsError(f"{source}: setting {leaf.name!r} got {value!r}: {reasons}") from None


_BOUNDS = {"greater_than_equal": ">=", "greater_than": ">", "less_than_equal": "<=", "less_than": "<"}


def _reason(error: Any) -> str:
    """A pydantic error as a person reads it: a range as ``must be >= 0``, anything else in pydantic's words."""
    sign = _BOUNDS.get(error["type"])
    if sign is None:
        return error["msg"]
    (bound,) = error["ctx"].values()
    return f"must be {sign} {bound}"


def check_ranges(settings: Any, prefix: str = "") -> None:
    """Refuse a value outside its field's range in settings built in code (:func:`load` checks what it reads),
    naming the value's flag; ``prefix``: the stem of a nested section's flags (``"demo_"``: ``--demo-steps``)."""
    for leaf in _leaves(type(settings)):
        if typing.get_origin(leaf.kind) is Annotated:
            value = settings
            for attr in leaf.path:
                value = getattr(value, attr)
            validated(leaf, value, flag(prefix + leaf.name))


def from_message(cls: type[T], values: typing.Mapping[str, Any], source: str) -> T:
    """A flat settings dataclass from a message's map (a reset's ``noise`` or ``latency``): unknown keys refused
    with the closest names, every value checked strictly against its field's type; the rest keep their defaults."""
    check_keys(dict(values), cls, source)
    leaves = {leaf.name: leaf for leaf in _leaves(cls)}
    checked = {name: validated(leaves[name], value, source, strict=True) for name, value in values.items()}
    for name, value in checked.items():
        numbers = value if isinstance(value, list | tuple) else [value]
        if any(isinstance(number, float) and not math.isfinite(number) for number in numbers):
            raise ValueError(f"{source}: setting {name!r} got {value!r}: a finite number is needed")
    return cls(**checked)


def read_tree(config_file: str | Path, cls: type) -> dict[str, Any]:
    """A settings file's YAML mapping, every key checked against the fields of ``cls``."""
    try:
        loaded = yaml.safe_load(Path(here_or_shipped(str(config_file))).read_text()) or {}
    except OSError as exc:
        raise SettingsError(f"--config {config_file}: {exc.strerror}") from None
    if not isinstance(loaded, dict):
        raise SettingsError(f"settings file {config_file} must hold a YAML mapping")
    check_keys(loaded, cls, f"settings file {config_file}")
    return loaded


def load(
    cls: type[T],
    args: argparse.Namespace | None = None,
    config_file: str | Path | None = None,
    environ: typing.Mapping[str, str] | None = None,
) -> T:
    """Build ``cls`` from defaults, then the YAML file, then ``SWIMM_*`` variables, then CLI flags."""
    environ = os.environ if environ is None else environ
    tree = read_tree(config_file, cls) if config_file else {}
    settings = cls()
    for leaf in _leaves(cls):
        value: Any = dataclasses.MISSING
        found, from_file = _from_file(tree, leaf, cls)
        if found:
            value = validated(leaf, from_file, f"settings file {config_file}")
        env_name = ENV_PREFIX + leaf.name.upper()
        if env_name in environ:
            source = f"environment variable {env_name}"
            try:
                text_value = _parse_text(leaf.kind, environ[env_name])
            except ValueError as exc:
                raise SettingsError(f"{source}: {exc}") from None
            value = validated(leaf, text_value, source)
        if args is not None and getattr(args, leaf.name, None) is not None:
            value = validated(leaf, getattr(args, leaf.name), flag(leaf.name))
        if value is not dataclasses.MISSING:
            _set(settings, leaf.path, value)
    return settings


def from_command_line(cls: type[T], argv: typing.Sequence[str], environ: typing.Mapping[str, str] | None = None) -> T:
    """``cls`` as a command reads it from its arguments ``argv`` (its flags and ``--config FILE``), then the
    ``SWIMM_*`` variables and the defaults: how `swimm up` reads each process's settings before it starts any."""
    parser = argparse.ArgumentParser()
    parser.add_argument("--config")
    add_arguments(parser, cls)
    args = parser.parse_args(argv)
    return load(cls, args, args.config, environ)


def to_dict(settings: Any) -> dict[str, Any]:
    """A YAML-friendly view of settings, for run folders."""
    return dataclasses.asdict(settings)
