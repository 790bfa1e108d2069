"""Configuration: one dataclass per service, a docstring on every field, and from it the CLI.

Precedence: dataclass defaults < `--config FILE.toml` < `TPDEB_*` environment variables <
command-line flags. Field `learning_rate` is flag `--learning-rate` and variable
`TPDEB_LEARNING_RATE`. Combinations are validated at start with the values in the message.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
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


class ConfigError(ValueError):
    """A bad setting; the message says which and what to do."""


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


def _field_type(cls, name: str):
    hint = typing.get_type_hints(cls)[name]
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
        if kind is int and isinstance(value, float) and value.is_integer():
            return int(value)
        if kind is int and isinstance(value, str):
            return int(float(value)) if "e" in value.lower() else int(value)
        return kind(value)
    except (TypeError, ValueError):
        raise ConfigError(
            f"{source}: {name}={value!r} is not a valid {getattr(kind, '__name__', kind)}"
        ) from None


def load_toml(path: str | Path, section: str | None = None) -> dict:
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"--config {path}: no such file")
    try:
        data = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"--config {path}: not valid TOML ({exc})") from None
    if section and isinstance(data.get(section), dict):
        data = data[section]
    return data


def build_parser(cls, prog: str, description: str) -> argparse.ArgumentParser:
    docs = field_docs(cls)
    parser = argparse.ArgumentParser(
        prog=prog, description=description,
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
    return parser


_OTHERS = "other service's "  # the dest prefix of the flags a service passes over


def training_names() -> set[str]:
    """Every training setting: a file (train.toml) may hold those a service does not use."""
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


def resolve(cls, argv: list[str] | None, prog: str, description: str, section: str | None = None):
    """Parse argv into a `cls` instance with the documented precedence."""
    parser = build_parser(cls, prog, description)
    args = {k: v for k, v in vars(parser.parse_args(argv)).items()
            if not k.startswith(_OTHERS)}
    names = {f.name for f in dataclasses.fields(cls)}
    values: dict = {}
    config_path = args.pop("config", None)
    if config_path:
        others = training_names()
        for key, value in load_toml(config_path, section).items():
            key = key.replace("-", "_")
            if key not in names:
                if isinstance(value, dict) or key in others:  # other services' settings
                    continue
                raise ConfigError(f"--config {config_path}: unknown setting {key!r}")
            values[key] = coerce(cls, key, value, f"--config {config_path}")
    for name in names:
        env_value = os.environ.get(ENV_PREFIX + name.upper())
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
    """Flat TOML of a config dataclass, readable back with --config."""
    lines = []
    for key, value in dataclasses.asdict(config).items():
        if isinstance(value, (list, tuple)):
            value = list(value)
        lines.append(f"{key} = {json.dumps(value)}")
    return "\n".join(lines) + "\n"
