"""`import alignrl` registers the Gymnasium ids, as docs/environments.md says, without
importing the environments or PyTorch; with gymnasium alone imported, the module-qualified
id `alignrl:alignrl/Focus-v0` makes Gymnasium import alignrl itself (Gymnasium 1.x loads no
plugins: a bare `alignrl/Focus-v0` cannot be known before alignrl is imported)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _python(script: str, where: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", script],
        cwd=where,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_import_alignrl_registers_the_ids_cheaply(tmp_path: Path) -> None:
    script = (
        "import sys\n"
        "import alignrl\n"
        "assert 'torch' not in sys.modules, 'torch was imported'\n"
        "assert 'alignrl.envs' not in sys.modules, 'the environments were imported'\n"
        "import gymnasium\n"
        "ids = [i for i in gymnasium.registry if i.startswith('alignrl/')]\n"
        "assert sorted(ids) == sorted(alignrl.GYMNASIUM_ENVS), ids\n"
        "env = gymnasium.make('alignrl/Focus-v0')\n"
        "observation, _ = env.reset(seed=0)\n"
        "print(type(env.unwrapped).__name__, observation.shape)\n"
        "family = gymnasium.make('alignrl/FocusFamily-v0', render_mode='rgb_array')\n"
        "print(family.unwrapped.task.quality_reference, family.unwrapped.render_mode)\n"
    )
    result = _python(script, tmp_path)  # not the checkout: the installed package
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.splitlines() == ["AlignmentEnv (8, 7)", "first rgb_array"]


def test_with_gymnasium_alone_the_module_qualified_id_is_made(tmp_path: Path) -> None:
    script = (
        "import gymnasium\n"
        "env = gymnasium.make('alignrl:alignrl/Stigmation-v0')\n"
        "print(env.spec.id, type(env.unwrapped).__name__)\n"
    )
    result = _python(script, tmp_path)
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == ["alignrl/Stigmation-v0", "AlignmentEnv"]


def test_the_environments_page_says_how_the_ids_are_registered() -> None:
    page = (ROOT / "docs" / "environments.md").read_text()
    assert "import alignrl  # registers alignrl/Focus-v0 and the rest" in page
    assert "import alignrl.envs  # registers" not in page
    assert 'gymnasium.make("alignrl:alignrl/Focus-v0")' in page
