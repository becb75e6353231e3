"""The README's gymnasium snippet runs as written in a fresh interpreter (no drivesim import before it)."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from sim_worlds import write_test_world

README = Path(__file__).resolve().parents[1] / "README.md"


def test_the_readme_gymnasium_snippet_makes_an_env(tmp_path: Path) -> None:
    blocks = re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)
    snippet = next(b for b in blocks if "gymnasium.make(" in b)
    write_test_world(tmp_path / "drivesim-work" / "world")
    # The procedural vehicle library instead of a built meshes/ folder (building one is not what this checks).
    code = snippet.replace('meshes="drivesim-work/meshes"', "meshes=None")
    code += "\nobs, info = env.reset(seed=0)\nprint(env.spec.id, obs.shape, sorted(info['state'])[:2])\n"
    done = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.startswith("drivesim/Overtake-v0 (3, 64, 160)")
