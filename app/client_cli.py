"""Moved to `app.client.cli`; this name stays for `app.cli`'s hook and `python -m app.client_cli`.
"""

from __future__ import annotations

import sys

from app.client.cli import main, register_client_commands

__all__ = ["main", "register_client_commands"]

if __name__ == "__main__":
    sys.exit(main())
