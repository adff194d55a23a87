"""Which code a benchmark measures.

An editable install (``pip install -e``, what the README's commands make) puts its
finder ahead of ``sys.path``: a benchmark script run from another checkout with
``PYTHONPATH=<checkout>`` still imports the installed tree's ``identify``, so a
"baseline at an older commit" measured that way is the installed code again. Each
benchmark therefore says which package it imported, at which commit, and warns when
that is not the checkout the script came from (install the other checkout into its own
environment to measure it)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path


def code_under_test(script: str) -> dict:
    import identify

    pkg = Path(identify.__file__).resolve().parent
    own = Path(script).resolve().parents[2]
    try:
        commit = subprocess.run(["git", "-C", str(pkg), "describe", "--always", "--dirty"],
                                capture_output=True, text=True, timeout=10).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    info = dict(package=str(pkg), commit=commit, same_checkout=pkg.parent == own)
    print(f"measuring identify from {pkg} ({commit or 'commit unknown'})", file=sys.stderr)
    if not info["same_checkout"]:
        print(f"WARNING: this script is from {own}, but identify comes from {pkg.parent}: "
              "the numbers are that tree's (an editable install's finder goes before PYTHONPATH)",
              file=sys.stderr)
    return info
