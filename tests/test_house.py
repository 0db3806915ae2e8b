"""The project speaks of itself alone: no development-process words in the tracked files' contents or names.

What is looked for: numbered work steps ("stop 28", "_stop29"), issue numbers in prose ("issue 13"), and remarks
on which machines were lent.  History lives in git; the tree says what was measured, on what machine, with which
command.
"""

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PROCESS_WORDS = re.compile(r"\bstops? [0-9]+(-[0-9]+)?\b|_stop[0-9]+|\bissues? [0-9]+\b|\bwas lent\b|\bsame session\b",
                           re.IGNORECASE)


def _tracked() -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: no list of tracked files")
    return [name for name in out.decode().split("\0") if name]


def test_no_tracked_file_speaks_of_the_development_process():
    found = []
    for name in _tracked():
        if name == "tests/test_house.py":  # the patterns themselves
            continue
        if PROCESS_WORDS.search(name):
            found.append(f"{name}: its name")
        path = ROOT / name
        if not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data[:8192]:  # binary (figures)
            continue
        for k, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), 1):
            if PROCESS_WORDS.search(line):
                found.append(f"{name}:{k}: {line.strip()[:120]}")
    assert not found, "\n".join(found[:20])
