"""Configuration: one dataclass per service, a docstring on every field, and from it the CLI.

Precedence: dataclass defaults < `--config FILE.toml` < `TPDEB_*` environment variables <
command-line flags. Field `learning_rate` is flag `--learning-rate` and variable
`TPDEB_LEARNING_RATE`. Combinations are validated at start with the values in the message.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import difflib
import functools
import inspect
import json
import os
import sys
import textwrap
import types
import typing
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

ENV_PREFIX = "TPDEB_"
# The tables of a TOML configuration, one per group of settings, in the order files list them.
SECTIONS = ("run", "actor", "model", "replay", "learner", "loss", "net", "router", "link")


class ConfigError(ValueError):
    """A bad setting; the message says which and what to do."""


# Settings that existed once and were removed, with what replaced them: refused by name wherever
# a setting can be given (flag, variable, file), never as merely "unknown".
RETIRED = {
    "loss_impl": "the loss is tpdeb_core/loss.py alone, differentiated by autograd and "
                 "compiled (the `compile` setting: auto | off); remove loss_impl",
}


def retired(name: str, source: str) -> ConfigError:
    return ConfigError(f"{source}: {name} was removed: {RETIRED[name]}")


@functools.cache
def field_docs(cls) -> dict[str, str]:
    """Attribute docstrings (the string literal right after each field) of a dataclass."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        body = tree.body[0].body
        for node, nxt in zip(body, body[1:], strict=False):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name)
                    and isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                    and isinstance(nxt.value.value, str)):
                docs[node.target.id] = " ".join(nxt.value.value.split())
    return docs


@functools.cache
def _hints(cls) -> dict:
    return typing.get_type_hints(cls)


def _field_type(cls, name: str):
    hint = _hints(cls)[name]
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):  # Optional[X] -> X
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        hint = args[0]
        origin = typing.get_origin(hint)
    if origin in (tuple, list):
        return list, typing.get_args(hint)[0]
    return hint, None


def coerce(cls, name: str, value, source: str):
    kind, item = _field_type(cls, name)
    try:
        if kind is list:
            if isinstance(value, str):
                value = value.replace(",", " ").split()
            # An empty string means no item: `--listen ""` clears an endpoint list.
            return tuple(item(v) for v in value if not (isinstance(v, str) and not v.strip()))
        if kind is bool:
            if isinstance(value, bool):
                return value
            text = str(value).strip().lower()
            if text in ("1", "true", "yes", "on"):
                return True
            if text in ("0", "false", "no", "off"):
                return False
            raise ValueError(value)
        if kind is str and isinstance(value, dict):  # a TOML table: its JSON text
            return json.dumps(value, sort_keys=True)
        if kind is int and isinstance(value, float) and value.is_integer():
            return int(value)
        if kind is int and isinstance(value, str):
            return int(float(value)) if "e" in value.lower() else int(value)
        return kind(value)
    except (TypeError, ValueError):
        raise ConfigError(
            f"{source}: {name}={value!r} is not a valid {getattr(kind, '__name__', kind)}"
        ) from None


def load_toml(path: str | Path, what: str = "--config") -> dict:
    """A TOML file's document; `what` names it in the errors (--config, preset)."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{what} {path}: no such file")
    try:
        return tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{what} {path}: not valid TOML ({exc})") from None


def section_of(cls, name: str) -> str:
    """The TOML table a field lives in: the `SECTION` of the group that first declares it."""
    for klass in reversed(cls.__mro__):
        if name in vars(klass).get("__annotations__", {}):
            return klass.SECTION
    raise KeyError(name)


def read_sections(cls, tables: dict, source: str, allowed: set[str] | None = None,
                  why: str = "") -> dict:
    """`cls`'s values from a sectioned TOML document, coerced. Every key must sit in its own
    group's table; the settings of other services' groups are checked and passed over, so one
    file can configure a whole run. `allowed`: the tables this document may have (`why` says
    why not others)."""
    known = {**known_settings(), **{f.name: section_of(cls, f.name)
                                    for f in dataclasses.fields(cls)}}
    sections = set(known.values()) if allowed is None else allowed
    names = {f.name for f in dataclasses.fields(cls)}
    values: dict = {}
    for section, table in tables.items():
        if not isinstance(table, dict):
            home = known.get(section.replace("-", "_"))
            hint = f"put it under [{home}]" if home else "settings sit in their group's table"
            raise ConfigError(f"{source}: {section} = {table!r} outside a table: {hint}")
        if section not in sections:
            raise ConfigError(f"{source}: no table [{section}] here{why}; expected "
                              f"{', '.join(f'[{s}]' for s in SECTIONS if s in sections)}")
        for key, value in table.items():
            key = key.replace("-", "_")
            if key in RETIRED:
                raise retired(key, f"{source} [{section}]")
            if key not in known:
                near = difflib.get_close_matches(key, known, n=1)
                hint = f" (did you mean {near[0]!r}?)" if near else ""
                raise ConfigError(f"{source} [{section}]: unknown setting {key!r}{hint}")
            if known[key] != section:
                raise ConfigError(f"{source} [{section}]: {key} belongs in [{known[key]}]")
            if key in names:
                values[key] = coerce(cls, key, value, f"{source} [{section}]")
    return values


@functools.cache
def known_settings() -> dict[str, str]:
    """Every setting of every service and of a training run, with its table (read-only)."""
    from tpdeb.services.config.service import SERVICE_CONFIGS
    from tpdeb.services.config.train import TrainConfig

    return {f.name: section_of(cls, f.name)
            for cls in (TrainConfig, *SERVICE_CONFIGS.values()) for f in dataclasses.fields(cls)}


def build_parser(cls, prog: str, description: str) -> argparse.ArgumentParser:
    docs = field_docs(cls)
    parser = argparse.ArgumentParser(
        prog=prog, description=description, allow_abbrev=False,
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--config", help="TOML file with any of the settings below")
    for f in _fields_derived_first(cls):
        kind, _ = _field_type(cls, f.name)
        flag = "--" + f.name.replace("_", "-")
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        help_text = docs.get(f.name, "")
        if kind is bool:
            parser.add_argument(flag, type=str, nargs="?", const="true", default=argparse.SUPPRESS,
                                metavar="BOOL", help=f"{help_text} (default: {default})")
        elif kind is list:
            parser.add_argument(flag, nargs="+", default=argparse.SUPPRESS,
                                help=f"{help_text} (default: {' '.join(map(str, default))})")
        else:
            parser.add_argument(flag, type=str, default=argparse.SUPPRESS,
                                metavar=kind.__name__.upper(),
                                help=f"{help_text} (default: {default})")
    # Other services' training settings are accepted and passed over (not listed): the same
    # command line, like the same train.toml, can be given to every service of a run.
    names = {f.name for f in dataclasses.fields(cls)}
    for name in sorted(training_names() - names) if "run_id" in names else ():
        parser.add_argument("--" + name.replace("_", "-"), nargs="*", default=argparse.SUPPRESS,
                            dest=f"{_OTHERS}{name}", help=argparse.SUPPRESS)
    for name in RETIRED:
        parser.add_argument("--" + name.replace("_", "-"), nargs="*", default=argparse.SUPPRESS,
                            dest=f"{_RETIRED}{name}", help=argparse.SUPPRESS)
    return parser


_OTHERS = "other service's "  # the dest prefix of the flags a service passes over
_RETIRED = "removed setting "  # and of those that no longer exist


def training_names() -> set[str]:
    """Every training setting: a command line may carry those a service does not use."""
    from tpdeb.services.config.train import TrainConfig

    return {f.name for f in dataclasses.fields(TrainConfig)}


def _fields_derived_first(cls) -> list:
    """The fields in the order --help shows them: the class's own first, then each base's (a
    service's settings before the network's, the training's before the loss's)."""
    owner: dict[str, int] = {}
    for rank, klass in enumerate(cls.__mro__):
        for name in vars(klass).get("__annotations__", {}):
            owner.setdefault(name, rank)
    return sorted(dataclasses.fields(cls), key=lambda f: owner.get(f.name, len(cls.__mro__)))


def resolve(cls, argv: list[str] | None, prog: str, description: str, environ=None):
    """Parse argv into a `cls` instance with the documented precedence (`environ`: the
    variables to read, os.environ by default)."""
    environ = os.environ if environ is None else environ
    parser = build_parser(cls, prog, description)
    args = {k: v for k, v in vars(parser.parse_args(argv)).items()
            if not k.startswith(_OTHERS)}
    for key in args:
        if key.startswith(_RETIRED):
            name = key[len(_RETIRED):]
            raise retired(name, "--" + name.replace("_", "-"))
    for name in RETIRED:
        if ENV_PREFIX + name.upper() in environ:
            raise retired(name, ENV_PREFIX + name.upper())
    names = {f.name for f in dataclasses.fields(cls)}
    values: dict = {}
    config_path = args.pop("config", None)
    if config_path:
        values.update(read_sections(cls, load_toml(config_path), f"--config {config_path}"))
    for name in names:
        env_value = environ.get(ENV_PREFIX + name.upper())
        if env_value is not None:
            values[name] = coerce(cls, name, env_value, ENV_PREFIX + name.upper())
    for name, value in args.items():
        values[name] = coerce(cls, name, value, "--" + name.replace("_", "-"))
    if "preset" in names:
        from tpdeb.services.config.presets import layer

        values = layer(cls, values)
    try:
        return cls(**values)
    except ConfigError:
        raise
    except ValueError as exc:  # __post_init__ validation
        raise ConfigError(str(exc)) from None


def to_toml(config) -> str:
    """A config dataclass as sectioned TOML, every field in its group's table, readable back
    with --config."""
    tables: dict[str, list[str]] = {}
    for key, value in dataclasses.asdict(config).items():
        if isinstance(value, (list, tuple)):
            value = list(value)
        tables.setdefault(section_of(type(config), key), []).append(
            f"{key} = {json.dumps(value)}")
    return "\n".join(f"[{name}]\n" + "\n".join(tables[name]) + "\n"
                     for name in SECTIONS if name in tables)


def flat(document: dict) -> dict:
    """A sectioned document's settings in one mapping (names are unique across tables; a
    setting outside any table is kept as it is)."""
    settings: dict = {}
    for key, value in document.items():
        settings.update(value if isinstance(value, dict) else {key: value})
    return settings
