"""The project speaks of itself alone: no development-process words in the tracked files' contents or names.

What is looked for: numbered work steps (the word for such a step followed by its number, in prose or in a file
name), issue numbers in prose, and remarks on which machines were lent for the work.  History lives in git; the
tree says what was measured, on what machine, with which command.
"""

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
# written in pieces, so that this file does not hold the phrases it looks for
PROCESS_WORDS = re.compile("|".join((r"\b" + "stop" + r"s? [0-9]+(-[0-9]+)?\b", "_" + "stop" + r"[0-9]+",
                                     r"\b" + "issue" + r"s? [0-9]+\b", r"\b" + "was" + r" lent\b",
                                     r"\b" + "same" + r" session\b")), re.IGNORECASE)


def _tracked() -> list[str]:
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True, timeout=60).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout: no list of tracked files")
    return [name for name in out.decode().split("\0") if name]


def test_no_tracked_file_speaks_of_the_development_process():
    found = []
    for name in _tracked():
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
