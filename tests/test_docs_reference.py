"""Issue 23: the reference pages made from the code stay what the code makes, and the README
and docs/performance.md name only paths that exist.

docs/reference/settings.md and docs/reference/errors.md are written by tools/gen_reference.py
from app/config/settings.py and app/errors.py (with app/client/errors.py). When a setting or
an error code changes, the tests here fail until the pages are written again:

    .venv/bin/python tools/gen_reference.py
"""

from __future__ import annotations

import importlib.util
import re
import sys
from pathlib import Path
from types import ModuleType

import pytest

from app.config import Settings, env_name
from app.errors import CODES

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
PERFORMANCE = ROOT / "docs" / "performance.md"
REFERENCE = ROOT / "docs" / "reference"


def _tool() -> ModuleType:
    path = ROOT / "tools" / "gen_reference.py"
    spec = importlib.util.spec_from_file_location("gen_reference", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("gen_reference", module)
    spec.loader.exec_module(module)
    return module


GEN = _tool()


@pytest.mark.parametrize("name", ["settings.md", "errors.md"])
def test_reference_page_is_what_the_generator_writes(name: str) -> None:
    path = REFERENCE / name
    render = GEN.TARGETS[path]
    diff = GEN.diff(path, render())
    assert not diff, (f"docs/reference/{name} differs from what tools/gen_reference.py "
                      f"generates; run `.venv/bin/python tools/gen_reference.py` and commit "
                      f"it:\n{diff[:4000]}")


def test_every_setting_and_every_code_has_its_row() -> None:
    settings = (REFERENCE / "settings.md").read_text(encoding="utf-8")
    for name in Settings.model_fields:
        assert f"| `{env_name(name)}` |" in settings, name
    errors = (REFERENCE / "errors.md").read_text(encoding="utf-8")
    for code, row in CODES.items():
        assert f"| `{code}` | {row.status if row.status is not None else '-'}" in errors, code


def test_the_generator_describes_every_setting() -> None:
    """A setting without a `#:` comment, a Field description, a flag's help or a note in the
    generator fails the generator (and so this test), naming it."""
    comments = GEN.field_comments(GEN.SETTINGS_SOURCE.read_text(encoding="utf-8"))
    flags = GEN.flag_helps()
    for name, info in Settings.model_fields.items():
        assert (comments.get(name) or info.description or flags.get(name, ("", ""))[1]
                or GEN.NOTES.get(name)), f"setting {name} has no description"
    assert set(GEN.NOTES) <= set(Settings.model_fields), "a note for no setting"


#: A path in the repository as the docs write it: `app/web/serving.py`, `bench/`, ...
_PATH = re.compile(r"(?<![\w./-])((?:app|protocol|kinematics|bench|examples|config|docs|tests|"
                   r"tools)/[\w./-]*)")


def _paths(text: str) -> set[str]:
    """Repository paths in backticks or markdown links (placeholders such as `<type>` cut
    the path there: `app/arms/<type>/` is checked as `app/arms/`)."""
    spans = re.findall(r"`([^`\n]+)`", text) + re.findall(r"\]\(([^)\s]+)\)", text)
    found: set[str] = set()
    for span in spans:
        for m in _PATH.finditer(span):
            found.add(m.group(1).rstrip(".,:;"))
    return found


@pytest.mark.parametrize("doc", [README, PERFORMANCE, *sorted(REFERENCE.glob("*.md"))],
                         ids=lambda p: str(p.relative_to(ROOT)))
def test_every_path_the_docs_name_exists(doc: Path) -> None:
    base = doc.parent
    missing = []
    for path in sorted(_paths(doc.read_text(encoding="utf-8"))):
        if not ((ROOT / path).exists() or (base / path).exists()):
            missing.append(path)
    assert not missing, f"{doc.relative_to(ROOT)} names paths that do not exist: {missing}"


def test_readme_points_to_the_docs() -> None:
    text = README.read_text(encoding="utf-8")
    layout = text.split("\n## Layout\n", 1)[1]
    assert "docs/architecture.md" in layout, "the Layout section points to docs/architecture.md"
    for target in ("docs/performance.md", "docs/reference/settings.md",
                   "docs/reference/errors.md"):
        assert f"]({target})" in text, f"the README links {target}"


def test_readme_performance_is_one_table_per_measure_not_a_diary() -> None:
    """Each measure under "## Performance" is one table, with the command and the date it
    ran; the history of runs lives in docs/performance.md."""
    text = README.read_text(encoding="utf-8")
    section = text.split("\n## Performance\n", 1)[1].split("\n## ", 1)[0]
    measures = section.split("\n### ")[1:]
    assert measures, "no measure under ## Performance"
    date = re.compile(r"\b\d{1,2} (?:Jan|Feb|Mar|Apr|May|Jun|Jul|Aug|Sep|Oct|Nov|Dec)[a-z]* "
                      r"\d{4}\b|\b\d{4}-\d{2}-\d{2}\b")
    for m in measures:
        title = m.splitlines()[0]
        tables = sum(1 for line in m.splitlines() if re.match(r"^\|[-| :]+\|$", line))
        assert tables == 1, f"{title!r}: {tables} tables (one per measure)"
        head = m.split("\n|", 1)[0]
        assert "`" in head and date.search(head), f"{title!r}: say the command and the date"
    diary = re.findall(r"\b(?:at|and at|again at) \d{1,2}:\d{2}\b", section)
    assert not diary, f"a diary of runs in the README's Performance: {diary}"
