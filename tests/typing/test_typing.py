"""A user's type checker sees the public API: mypy reports every deliberate misuse of
tests/typing/misuse.py, one error on each line marked `# misuse`, and nothing else."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

MISUSE = Path(__file__).with_name("misuse.py")


@pytest.mark.slow
def test_mypy_reports_each_misuse_once(tmp_path):
    pytest.importorskip("mypy")
    result = subprocess.run([sys.executable, "-m", "mypy", "--follow-imports=silent", "--cache-dir",
                             str(tmp_path / "cache"), "--no-color-output", str(MISUSE)],
                            capture_output=True, text=True, cwd=MISUSE.parents[2])
    reported = [int(m.group(1)) for m in re.finditer(r"misuse\.py:(\d+): error:", result.stdout)]
    marked = [i for i, line in enumerate(MISUSE.read_text().splitlines(), 1) if line.endswith("# misuse")]
    assert len(marked) >= 5
    assert sorted(reported) == marked, result.stdout
