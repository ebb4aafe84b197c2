"""Issue 22.12: the README's table of settings ("## Configuration") says every setting of
app/config/settings.py with its true default, so the two cannot drift apart again."""

from __future__ import annotations

import re
from pathlib import Path

from app.config import Settings, env_name

README = Path(__file__).resolve().parent.parent / "README.md"


def readme_table() -> dict[str, str]:
    """ARMSERVER_* name -> the default the README gives, as written (backticks dropped)."""
    text = README.read_text(encoding="utf-8")
    section = text.split("\n## Configuration\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| `ARMSERVER_")]
    assert rows, "no settings table under ## Configuration"
    table: dict[str, str] = {}
    for line in rows:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        names = re.findall(r"`([A-Z0-9_]+)`", cells[0])
        full: list[str] = []
        for n in names:  # `ARMSERVER_MQTT_URL`, `_PREFIX`: the first's stem and the suffix
            full.append(full[0].rsplit("_", 1)[0] + n if n.startswith("_") else n)
        defaults = [d.strip() for d in cells[1].split(",")]
        if len(defaults) == 1:
            defaults *= len(full)
        assert len(defaults) == len(full), f"README row {line!r}: one default per variable"
        for name, default in zip(full, defaults, strict=True):
            assert name not in table, f"{name} twice in the README table"
            table[name] = default.strip("`")
    return table


def written(default: object) -> str:
    """A default as the README writes it."""
    if default is None or default == "":
        return "none"
    if isinstance(default, bool):
        return str(default).lower()
    if isinstance(default, float) and default.is_integer():
        return str(int(default))
    return str(default)


def test_every_setting_is_in_the_readme_with_its_true_default() -> None:
    table = readme_table()
    fields = {env_name(name): info.default for name, info in Settings.model_fields.items()}
    missing = sorted(set(fields) - set(table))
    unknown = sorted(set(table) - set(fields))
    wrong = {name: (table[name], written(default)) for name, default in fields.items()
             if name in table and not (table[name] == written(default) or (
                 written(default) == "none" and table[name].startswith("none")))}
    # settings missing from the table; rows for no setting; {name: (README's, settings.py's)}
    assert (missing, unknown, wrong) == ([], [], {})
