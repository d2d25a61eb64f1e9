"""The project's shape, as the README states it: the numerics in ``bms_estimator/core/`` take arrays in and give
arrays out, with no I/O; files, buses, brokers and logs are the edges' (README, "The method in brief")."""

import ast
from pathlib import Path

CORE = Path(__file__).resolve().parents[1] / "bms_estimator" / "core"

#: what the core may import: the language's pure helpers and the numerics
CORE_IMPORTS = {"__future__", "annotated_types", "collections", "dataclasses", "enum", "functools", "itertools",
                "math", "numpy", "operator", "scipy", "typing", "warnings"}
#: calls that touch a file, a process or the clock
IO_CALLS = {"open", "read_text", "write_text", "read_bytes", "write_bytes", "mkdir", "unlink", "print", "input",
            "loadtxt", "savetxt", "genfromtxt", "load", "save", "savez", "fromfile", "tofile"}


def _core_modules() -> list[Path]:
    files = sorted(CORE.glob("*.py"))
    assert len(files) > 10, files  # the core is there
    return files


def test_the_core_imports_no_io_module():
    """A core module that imported pathlib, os, io, logging, can or an MQTT client would be an edge
    (core/ocv.py read and wrote its tables' files until they moved to ocv_table.py)."""
    found = []
    for path in _core_modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0:
                names = [node.module or ""]
            else:
                continue
            found += [f"{path.name}: {n}" for n in names if n.split(".")[0] not in CORE_IMPORTS]
    assert not found, found


def test_the_core_calls_nothing_that_reads_or_writes_a_file():
    found = []
    for path in _core_modules():
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Call):
                f = node.func
                name = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
                if name in IO_CALLS:
                    found.append(f"{path.name}:{node.lineno}: {name}()")
    assert not found, found
