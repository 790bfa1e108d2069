"""SPEC §1: imports go one way, and the algorithm layer does no I/O."""

import ast
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# tpdeb_core: torch, numpy and side-effect-free standard modules only (no files, no clocks)
CORE_ALLOWED = {"torch", "numpy", "tpdeb_core", "__future__", "math", "copy", "dataclasses",
                "typing", "collections", "abc", "itertools", "functools", "enum", "numbers"}
PROTOCOL_ALLOWED = {"numpy", "msgpack", "zstandard", "protocol", "__future__", "dataclasses",
                    "typing", "collections", "math", "re", "itertools", "functools", "enum"}


def imported_roots(package: str) -> dict[str, set[str]]:
    found = {}
    for path in (ROOT / package).rglob("*.py"):
        roots = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                roots |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                roots.add(node.module.split(".")[0])
        found[str(path.relative_to(ROOT))] = roots
    return found


def test_core_imports_only_torch_numpy_and_pure_stdlib():
    modules = imported_roots("tpdeb_core")
    assert modules, "tpdeb_core has no modules"
    bad = {m: sorted(r - CORE_ALLOWED) for m, r in modules.items() if r - CORE_ALLOWED}
    assert not bad, f"tpdeb_core must stay pure (no I/O, no services/protocol): {bad}"


def test_protocol_imports_only_numpy_msgpack_zstandard_and_pure_stdlib():
    # no services, no core, no torch, no Zenoh: the wire format knows bytes and names only
    bad = {m: sorted(r - PROTOCOL_ALLOWED) for m, r in imported_roots("protocol").items()
           if r - PROTOCOL_ALLOWED}
    assert not bad, bad


def test_layout_directories_exist():
    for name in ("tpdeb_core", "protocol", "services", "deploy", "tests", "bench"):
        assert (ROOT / name).is_dir(), name


def test_router_link_and_launcher_start_without_torch():
    # they only route, shape or supervise: torch would add over 200 MiB to each
    code = ("import sys, services.router, services.link, services.cluster; "
            "services.router.RouterConfig(); "  # validating a config must not need it either
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "False"
