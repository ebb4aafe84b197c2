"""What the test suite needs from outside Python, and the one way it is found: the tests import
the paths below, and the Makefile runs this file (with the system python3, before any venv) to
learn which Debian packages to install and to fail if anything is still missing afterwards.

    python3 tests/_deps.py packages chromium node   # Debian packages of the missing ones, one line
    python3 tests/_deps.py check chromium node      # exit 1, naming what is missing

A program is found on the PATH, then in the directories Debian installs it in (mosquitto is in
/usr/sbin, outside a plain user's PATH); a header (Python.h) in the include directory of the
interpreter that runs this file (the one the venv is made from). Standard library only.
"""

from __future__ import annotations

import os
import shutil
import sys
import sysconfig

#: name -> (the Debian package that provides it, what needs it)
TOOLS: dict[str, tuple[str, str]] = {
    "chromium": ("chromium", "the dashboard's browser tests (tests/test_*_e2e.py)"),
    "mosquitto": ("mosquitto", "the MQTT tests and `make run-lab`"),
    "mosquitto_passwd": ("mosquitto", "the MQTT tests with accounts (test_mqtt*.py)"),
    "node": ("nodejs", "the dashboard's JavaScript kinematics (test_arm_registry.py)"),
    "stress-ng": ("stress-ng", "`make test-loaded`, the suite beside a CPU load"),
    "cc": ("gcc", "the poll thread's rounds in C (app/links/_restpoll.c), built at install"),
    "Python.h": ("python3-dev", "the same, against this interpreter's headers"),
}

_EXTRA_DIRS = ("/usr/local/bin", "/usr/bin", "/usr/local/sbin", "/usr/sbin", "/sbin", "/bin")


def find(name: str) -> str | None:
    """The path of program `name` (a header, `*.h`: in this interpreter's include directory),
    or None."""
    if name.endswith(".h"):
        header = os.path.join(sysconfig.get_paths()["include"], name)
        return header if os.path.exists(header) else None
    path = os.environ.get("PATH", "")
    return shutil.which(name, path=os.pathsep.join([path, *_EXTRA_DIRS]))


CHROMIUM = find("chromium")
MOSQUITTO = find("mosquitto")
MOSQUITTO_PASSWD = find("mosquitto_passwd")
NODE = find("node")


def missing_message(name: str) -> str:
    """The reason a test gives when it cannot run for want of `name`."""
    package, _ = TOOLS[name]
    return (f"{name} is missing: `make test` installs Debian's {package} (as root, or with "
            f"`sudo apt-get install {package}`)")


def main(argv: list[str]) -> int:
    if len(argv) < 2 or argv[1] not in ("packages", "check"):
        print(__doc__, file=sys.stderr)
        return 2
    names = argv[2:] or list(TOOLS)
    unknown = [n for n in names if n not in TOOLS]
    if unknown:
        print(f"unknown tool(s): {' '.join(unknown)}", file=sys.stderr)
        return 2
    missing = [n for n in names if find(n) is None]
    if argv[1] == "packages":
        packages = dict.fromkeys(TOOLS[n][0] for n in missing)
        if packages:
            print(" ".join(packages))
        return 0
    for n in missing:
        print(f"error: {n} not found ({TOOLS[n][1]}); install Debian's {TOOLS[n][0]}",
              file=sys.stderr)
    return 1 if missing else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
