"""The layers: imports go one way, and the algorithm layer does no I/O."""

import ast
from pathlib import Path

from tests.procs import python_c

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]

# tpdeb_core: torch, numpy and side-effect-free standard modules only (no files, no clocks)
CORE_ALLOWED = {"torch", "numpy", "tpdeb_core", "__future__", "math", "copy", "dataclasses",
                "typing", "collections", "abc", "itertools", "functools", "enum", "numbers"}
PROTOCOL_ALLOWED = {"numpy", "msgpack", "zstandard", "protocol", "__future__", "dataclasses",
                    "typing", "collections", "math", "re", "itertools", "functools", "enum"}
# The one edge between the two: the fragment's schema. The data's shape is the algorithm's, the
# wire validates it (DESIGN §1); that module imports no other of ours.
FRAGMENT_SCHEMA = "tpdeb.tpdeb_core.schema"


def root_of(module: str) -> str:
    """`numpy.linalg` → numpy; our own `tpdeb.protocol.codec` → protocol (the layer)."""
    parts = module.split(".")
    return parts[1] if parts[0] == "tpdeb" and len(parts) > 1 else parts[0]


def imported_modules(package: str) -> dict[str, set[str]]:
    """Every module each file of `package` imports (`from m import x` counts as m)."""
    found = {}
    for path in (ROOT / package).rglob("*.py"):
        modules = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                modules |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                modules.add(node.module)
        found[str(path.relative_to(ROOT))] = modules
    return found


def imported_roots(package: str) -> dict[str, set[str]]:
    return {path: {root_of(m) for m in modules}
            for path, modules in imported_modules(package).items()}


def test_our_modules_import_each_other_under_the_installed_name():
    """Inside the repository `services`, `protocol` and `tpdeb_core` are also importable as
    top-level names; importing them so would load a second copy of every module."""
    bare = {}
    for package in ("tpdeb_core", "protocol", "services", "bench", "tests"):
        for path in imported_roots(package):
            text = (ROOT / path).read_text()
            found = [line for line in text.splitlines() if line.lstrip().startswith(
                ("from services", "from protocol", "from tpdeb_core", "import services",
                 "import protocol", "import tpdeb_core"))]
            if found:
                bare[path] = found
    assert not bare, bare


def test_core_imports_only_torch_numpy_and_pure_stdlib():
    modules = imported_roots("tpdeb_core")
    assert modules, "tpdeb_core has no modules"
    bad = {m: sorted(r - CORE_ALLOWED) for m, r in modules.items() if r - CORE_ALLOWED}
    assert not bad, f"tpdeb_core must stay pure (no I/O, no services/protocol): {bad}"


def test_protocol_imports_only_numpy_msgpack_zstandard_pure_stdlib_and_the_fragment_schema():
    # no services, no torch, no Zenoh, of the core only the fragment's schema
    bad = {}
    for path, modules in imported_modules("protocol").items():
        wrong = {m for m in modules if m != FRAGMENT_SCHEMA and root_of(m) not in PROTOCOL_ALLOWED}
        if wrong:
            bad[path] = sorted(wrong)
    assert not bad, bad
    schema = imported_modules("tpdeb_core")["tpdeb_core/schema.py"]
    ours = sorted(m for m in schema if m.split(".")[0] == "tpdeb")
    assert not ours, f"tpdeb_core/schema.py imports {ours}: protocol would load them too"
    out = python_c("import sys, tpdeb.protocol; print(sorted(m for m in sys.modules "
                   "if m.startswith('tpdeb.tpdeb_core.')), 'torch' in sys.modules)")
    assert out.stdout.split() == [f"['{FRAGMENT_SCHEMA}']", "False"], out.stdout + out.stderr


def test_the_wheel_installs_one_top_level_name(tmp_path):
    """`services` and `protocol` are names any project may use: the wheel puts everything under
    `tpdeb` (with the cluster file and the presets), nothing beside it."""
    import shutil
    import subprocess
    import sys
    import zipfile

    source = tmp_path / "source"  # a copy: building leaves build/ and *.egg-info behind
    for name in ("tpdeb_core", "protocol", "services", "deploy"):
        shutil.copytree(ROOT / name, source / name,
                        ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, source / name)
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps",
                          "--no-build-isolation", "-q", "-w", str(tmp_path), str(source)],
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    (wheel,) = tmp_path.glob("tpdeb-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    tops = {name.split("/")[0] for name in names}
    assert tops == {"tpdeb", wheel.name.split("-py")[0] + ".dist-info"}, tops
    for needed in ("tpdeb/services/learner.py", "tpdeb/protocol/codec.py",
                   "tpdeb/tpdeb_core/learner.py", "tpdeb/deploy/local.toml",
                   "tpdeb/deploy/presets/HalfCheetah-v5.toml",
                   "tpdeb/deploy/presets/race/Walker2d-v5.toml"):
        assert needed in names, needed


def test_layout_directories_exist():
    for name in ("tpdeb_core", "protocol", "services", "deploy", "tests", "bench"):
        assert (ROOT / name).is_dir(), name


# The entry points that train or evaluate a network; every other one must not load torch (over
# 200 MiB and a second of start-up per process: actors act with numpy, the replay never runs a
# network).
TORCH_ENTRY_POINTS = {"tpdeb-learner", "tpdeb-train", "tpdeb-eval"}


def entry_points() -> dict[str, str]:
    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    return {name: target.split(":")[0] for name, target in scripts.items()}


def test_the_entry_points_are_known():
    assert entry_points().keys() >= TORCH_ENTRY_POINTS
    assert {"tpdeb-actor", "tpdeb-replay", "tpdeb-router", "tpdeb-link",
            "tpdeb-cluster", "tpdeb-health"} <= entry_points().keys()


def test_only_the_training_and_evaluating_entry_points_import_torch():
    modules = entry_points()
    found = {}
    for name, module in modules.items():
        out = python_c(f"import {module}, sys; print('torch' in sys.modules)")
        found[name] = out.stdout.strip() == "True"
    light = sorted(name for name, has in found.items() if has and name not in TORCH_ENTRY_POINTS)
    assert not light, f"these entry points import torch: {light}"
    assert found["tpdeb-learner"] and found["tpdeb-train"]  # the check sees torch where it is


def test_router_config_validates_without_torch():
    code = ("import sys, tpdeb.services.router; tpdeb.services.config.service.RouterConfig(); "
            "print('torch' in sys.modules)")
    assert python_c(code).stdout.strip() == "False"


def test_functions_stay_short_and_no_process_imports_the_serial_runner():
    """Every function of the algorithm, the wire and the services reads on one screen."""
    long, serial = [], []
    for package in ("tpdeb_core", "protocol", "services"):
        for path in (ROOT / package).rglob("*.py"):
            tree = ast.parse(path.read_text())
            for node in ast.walk(tree):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    if node.end_lineno - node.lineno + 1 > 60:
                        long.append(f"{package}/{path.name}:{node.name}")
                elif isinstance(node, ast.ImportFrom) and node.module == "tpdeb.services.serial":
                    serial.append(path.name)
    assert not long, f"functions over 60 lines: {long}"
    assert not serial, f"these modules import the serial runner: {serial}"
