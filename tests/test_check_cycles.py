"""tools/check_cycles.py (run by `make lint`): it finds a cycle, says which, and app/ has none
beyond the tolerated ones."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
TOOL = ROOT / "tools" / "check_cycles.py"


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, str(TOOL), *args], cwd=cwd, capture_output=True,
                          text=True, timeout=60, check=False)


def _package(tmp_path: Path, files: dict[str, str]) -> Path:
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    for name, text in files.items():
        (pkg / name).write_text(text)
    return pkg


def test_a_cycle_fails_and_is_named(tmp_path: Path) -> None:
    _package(tmp_path, {
        "a.py": "from pkg import b\n",
        "b.py": "def f():\n    from pkg.c import g\n    return g\n",  # deferred: still an edge
        "c.py": "from pkg.a import b as _b\ndef g():\n    return 1\n",
    })
    r = _run("pkg", cwd=tmp_path)
    assert r.returncode == 1, r.stdout
    assert "import cycle: pkg.a -> pkg.b -> pkg.c -> pkg.a" in r.stdout


def test_type_only_imports_count_only_with_types(tmp_path: Path) -> None:
    _package(tmp_path, {
        "a.py": "from pkg import b\n",
        "b.py": "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from pkg import a\n",
    })
    assert _run("pkg", cwd=tmp_path).returncode == 0
    r = _run("--types", "pkg", cwd=tmp_path)
    assert r.returncode == 1 and "pkg.a -> pkg.b -> pkg.a" in r.stdout


def test_app_has_no_cycle_beyond_the_tolerated_ones() -> None:
    r = _run("app", cwd=ROOT)
    assert r.returncode == 0, r.stdout
    assert "app.arms" not in r.stdout
