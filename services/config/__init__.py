"""Configuration: one dataclass per service, a docstring on every field, and from it the CLI.

Precedence: dataclass defaults < `--config FILE.toml` (a settings file) < `TPDEB_*` environment
variables < command-line flags and `--set key=value`. Field `learning_rate` is flag
`--learning-rate`, `--set learning_rate=…` and variable `TPDEB_LEARNING_RATE`, for every command
that trains or serves. A name that is no setting is refused in one line with the closest one.
Combinations are validated at start with the values in the message.
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
SECTIONS = ("run", "actor", "model", "replay", "learner", "loss", "eval", "net", "router",
            "link")


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


# TPDEB_* variables that are no setting: the deploy files' own (docker-compose.yml's image and
# torch wheel, the Slurm script's layout) and the test suite's. Any other TPDEB_* variable that
# names no setting is a typo, refused rather than silently ignored.
OTHER_VARIABLES = ("IMAGE", "TORCH_SPEC", "ROUTER_HOST", "ROUTER_PORT", "PORT", "ACTORS_PER_NODE",
                   "KEEP_FIGURES", "FUZZ_EXAMPLES")


def closest(name: str, names) -> str:
    """' (did you mean X?)' for the nearest of `names`, or ''."""
    near = difflib.get_close_matches(name, list(names), n=1)
    return f" (did you mean {near[0]!r}?)" if near else ""


def unknown_setting(key: str, source: str) -> ConfigError:
    """The one refusal of a name that is no setting, wherever it was given."""
    if key in RETIRED:
        return retired(key, source)
    return ConfigError(f"{source}: unknown setting {key!r}{closest(key, known_settings())}")


def check_environment(environ) -> None:
    """Refuse a TPDEB_* variable that names no setting (one line, with the closest name)."""
    known = {ENV_PREFIX + name.upper() for name in known_settings()}
    known |= {ENV_PREFIX + name for name in (*OTHER_VARIABLES, "PASSWORD")}
    for name in sorted(environ):
        if not name.startswith(ENV_PREFIX) or name in known:
            continue
        setting = name[len(ENV_PREFIX):].lower()
        if setting in RETIRED:
            raise retired(setting, name)
        raise ConfigError(f"{name}: no setting is named {setting!r}"
                          f"{closest(name, sorted(known))}; unset it")


def parse_sets(items, own=(), source: str = "--set") -> dict[str, str]:
    """`--set KEY=VALUE` items as {setting: text}, every key a setting of some service (or one
    of `own`, the command's)."""
    values: dict[str, str] = {}
    for item in items or ():
        key, sep, value = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or not key:
            raise ConfigError(f"{source} {item!r}: expected KEY=VALUE, e.g. --set "
                              "learning_rate=3e-4")
        if key not in known_settings() and key not in own:
            raise unknown_setting(key, f"{source} {key}")
        values[key] = value.strip()
    return values


def is_cluster_file(document: dict) -> bool:
    """Whether a TOML document is a cluster file (its tables) rather than a settings file."""
    return bool({"services", "cluster", "train"} & set(document))


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
            if key not in known:
                raise unknown_setting(key, f"{source} [{section}]")
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


class Parser(argparse.ArgumentParser):
    """Every command's parser: a flag it does not know is refused in one line with the closest
    flag (not argparse's usage block); `--help` shows the rest."""

    def __init__(self, **kwargs):
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(**kwargs)

    def error(self, message: str):
        hint = ""
        if message.startswith("unrecognized arguments"):
            flags = [a for a in message.split(":", 1)[1].split() if a.startswith("--")]
            options = [o for o in self._option_string_actions if o.startswith("--")
                       and self._option_string_actions[o].help != argparse.SUPPRESS]
            if flags:
                hint = closest(flags[0].partition("=")[0], options)
        self.exit(2, f"{self.prog}: error: {message}{hint} ({self.prog} --help lists the "
                     "flags)\n")


SET_HELP = "any setting by name, e.g. --set learning_rate=3e-4 (repeatable; as its flag)"
CONFIG_HELP = "settings file (TOML with any of the settings below, e.g. a run's config.toml)"


def build_parser(cls, prog: str, description: str) -> argparse.ArgumentParser:
    parser = Parser(prog=prog, description=description,
                    formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    parser.add_argument("--config", help=CONFIG_HELP)
    parser.add_argument("--set", action="append", metavar="KEY=VALUE", default=argparse.SUPPRESS,
                        help=SET_HELP)
    add_setting_flags(parser, cls)
    return parser


def add_setting_flags(parser: argparse.ArgumentParser, cls) -> None:
    """A flag per field of `cls` (`--learning-rate`), documented by the field's docstring; the
    flags of other services' training settings, accepted and passed over; retired ones."""
    docs = field_docs(cls)
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


_OTHERS = "other service's "  # the dest prefix of the flags a service passes over
_RETIRED = "removed setting "  # and of those that no longer exist


def refuse_retired(args: dict) -> None:
    """A parsed flag of a removed setting, refused with what replaced it."""
    for key in args:
        if key.startswith(_RETIRED):
            name = key[len(_RETIRED):]
            raise retired(name, "--" + name.replace("_", "-"))


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


def resolve(cls, argv: list[str] | None, prog: str, description: str, environ=None,
            base: dict | None = None):
    """Parse argv into a `cls` instance with the documented precedence (`environ`: the
    variables to read, os.environ by default; `base`: settings under the --config file's, of
    which `cls`'s own are taken)."""
    environ = os.environ if environ is None else environ
    parser = build_parser(cls, prog, description)
    args = {k: v for k, v in vars(parser.parse_args(argv)).items()
            if not k.startswith(_OTHERS)}
    names = {f.name for f in dataclasses.fields(cls)}
    refuse_retired(args)
    check_environment(environ)
    sets = parse_sets(args.pop("set", ()), names)
    values = {k: v for k, v in (base or {}).items() if k in names}
    config_path = args.pop("config", None)
    if config_path:
        values.update(read_settings_file(cls, config_path))
    for name in names:
        env_value = environ.get(ENV_PREFIX + name.upper())
        if env_value is not None:
            values[name] = coerce(cls, name, env_value, ENV_PREFIX + name.upper())
    for name, value in args.items():
        values[name] = coerce(cls, name, value, "--" + name.replace("_", "-"))
    for name, value in sets.items():
        if name in names:  # another service's setting is passed over, as its flag is
            values[name] = coerce(cls, name, value, f"--set {name}")
    if "preset" in names:
        from tpdeb.services.config.presets import layer

        values = layer(cls, values)
    try:
        return cls(**values)
    except ConfigError:
        raise
    except ValueError as exc:  # __post_init__ validation
        raise ConfigError(str(exc)) from None


def read_settings_file(cls, path) -> dict:
    """`cls`'s values from a settings file (`--config`); a cluster file is named as one."""
    document = load_toml(path)
    if is_cluster_file(document):
        raise ConfigError(f"--config {path} is a cluster file (it has "
                          f"{', '.join(f'[{t}]' for t in sorted(document))}): tpdeb-cluster "
                          "takes it as --cluster-file; --config takes a settings file")
    return read_sections(cls, document, f"--config {path}")


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
