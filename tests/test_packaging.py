"""The project as a user installs it: the built wheel, not the checkout."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_wheel_installs_and_runs_the_readme_snippet():
    # .ci/wheel-check builds the wheel, installs it into a fresh environment and runs
    # README's first snippet from outside the repository; it fails if any package the
    # snippet needs (models.cpds among them) is missing from the wheel.
    env = os.environ | {"PY": sys.executable}
    done = subprocess.run(
        [str(ROOT / ".ci" / "wheel-check")], env=env, capture_output=True, text=True
    )
    assert done.returncode == 0, done.stdout + done.stderr
    assert "installs and runs README's first snippet" in done.stdout
