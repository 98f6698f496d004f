"""Each loopback address a test starts a simulator or a server on belongs to one test file:
`make test` runs the files on two workers at once (`--dist loadfile`), and two files on one
address fail whichever starts second ("simulated UR controller did not start"). 127.0.0.94 was
in two files until 2026-11-29, an intermittent CI failure that never showed with either file
alone (a report-only audit of the tests under load found it)."""

from __future__ import annotations

import re
from collections import defaultdict
from pathlib import Path

HERE = Path(__file__).parent
# addresses that appear as text only (a recorded URL compared, an argument refused before any
# connection), never connected to: file name -> addresses
TEXT_ONLY = {"test_resume.py": {"127.0.0.2"}}


def test_no_loopback_address_is_shared_by_two_test_files():
    files = defaultdict(set)
    for p in sorted(HERE.glob("*.py")):
        if p.name == Path(__file__).name:
            continue
        for a in re.findall(r"\b127\.0\.0\.(\d+)\b", p.read_text()):
            addr = f"127.0.0.{a}"
            if addr != "127.0.0.1" and addr not in TEXT_ONLY.get(p.name, set()):
                files[addr].add(p.name)
    shared = {a: sorted(f) for a, f in files.items() if len(f) > 1}
    assert not shared, shared
