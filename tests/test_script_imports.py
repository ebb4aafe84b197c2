"""Every script under bench/ and examples/ imports only names the project still has.

The scripts are not imported by the suite (most start servers or run for minutes), and mypy
checks app/, not them: when 58e7d87 moved `load_profile` from app.config to app.arms.loading,
bench/hostile.py and bench/envelope.py failed at their first line for days. Each script's
`from <project module> import name` is resolved here as Python would: the module imported, the
name found on it (or a submodule of that name).
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
#: The project's packages (a script's own helpers, bench/_server.py and the like, are its).
PROJECT = ("app", "protocol", "kinematics")
SCRIPTS = sorted([*ROOT.glob("bench/*.py"), *ROOT.glob("examples/*.py")])


def _fallbacks(tree: ast.AST) -> set[ast.AST]:
    """The nodes under an `except ImportError:` (a script's imports for an older layout, as
    bench/goal_trace.py's for `--root` of 0.3.0): they are meant not to resolve here."""
    out: set[ast.AST] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Try):
            for h in node.handlers:
                if h.type is not None and "ImportError" in ast.unparse(h.type):
                    out.update(n for stmt in h.body for n in ast.walk(stmt))
    return out


def project_imports(path: Path) -> list[tuple[int, str, str | None]]:
    """(line, module, name) of each import of a project module in `path`; name None for a
    plain `import module`."""
    found: list[tuple[int, str, str | None]] = []
    tree = ast.parse(path.read_text(), str(path))
    skip = _fallbacks(tree)
    for node in ast.walk(tree):
        if node in skip:
            continue
        if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module and \
                node.module.split(".")[0] in PROJECT:
            found += [(node.lineno, node.module, a.name) for a in node.names]
        elif isinstance(node, ast.Import):
            found += [(node.lineno, a.name, None) for a in node.names
                      if a.name.split(".")[0] in PROJECT]
    return found


def unresolved(path: Path) -> list[str]:
    missing = []
    for line, module, name in project_imports(path):
        try:
            mod = importlib.import_module(module)
        except ImportError as exc:
            missing.append(f"{path.name}:{line}: import {module}: {exc}")
            continue
        if name is None or name == "*" or hasattr(mod, name):
            continue
        try:
            importlib.import_module(f"{module}.{name}")
        except ImportError:
            missing.append(f"{path.name}:{line}: {module} has no {name!r}")
    return missing


def test_the_scripts_are_found() -> None:
    names = {p.name for p in SCRIPTS}
    assert {"hostile.py", "lab.py", "peers.py", "sort_colors.py"} <= names
    assert sum(len(project_imports(p)) for p in SCRIPTS) > 50


@pytest.mark.parametrize("path", SCRIPTS, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_each_script_imports_only_names_the_project_has(path: Path) -> None:
    assert unresolved(path) == []


def test_a_moved_name_is_caught(tmp_path: Path) -> None:
    script = tmp_path / "old.py"
    script.write_text("from app.config import KeepOutBox, load_profile\n"
                      "import app.no_such_module\n"
                      "from app.arms.loading import load_profile as lp\n"
                      "try:\n    from app.web.factory import create_app\n"
                      "except ImportError:\n    from app.main import create_app\n")
    assert unresolved(script) == [
        "old.py:1: app.config has no 'load_profile'",
        "old.py:2: import app.no_such_module: No module named 'app.no_such_module'",
    ]
