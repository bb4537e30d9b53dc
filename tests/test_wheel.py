"""A wheel of alignrl carries its shipped champions: built with `pip wheel` (no network, no
build isolation) from a copy of the package, it lists every champion's files, and unpacked
outside the repository it runs `alignrl align --policy champion:focus-v1` from them. The
unpacked folder comes first on PYTHONPATH, so the import must find it there, not through the
editable install's finder (which maps alignrl to this checkout)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

from alignrl.runs.sources import shipped_champions

ROOT = Path(__file__).resolve().parent.parent
CHAMPION_FILES = ("card.json", "model_card.md", "policy.safetensors")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """alignrl's wheel, built from a copy of what the build reads (the checkout stays clean:
    no build/ or egg-info written into it)."""
    folder = tmp_path_factory.mktemp("wheel")
    source = folder / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", ".*")
    shutil.copytree(ROOT / "alignrl", source / "alignrl", ignore=ignore)
    command = [sys.executable, "-m", "pip", "wheel", str(source), "--no-deps", "--quiet"]
    command += ["--no-build-isolation", "--no-index", "-w", str(folder / "dist")]  # no network
    built = subprocess.run(
        command,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert built.returncode == 0, built.stderr[-3000:]
    (path,) = (folder / "dist").glob("alignrl-*.whl")
    return path


def test_the_wheel_holds_every_champion(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    assert "alignrl/champions/focus-v1/policy.safetensors" in names
    assert "alignrl/champions/README.md" in names
    for champion in shipped_champions():
        for file in CHAMPION_FILES:
            assert f"alignrl/champions/{champion}/{file}" in names, (champion, file)


def test_the_wheel_holds_every_family_and_instrument(wheel: Path) -> None:
    names = set(zipfile.ZipFile(wheel).namelist())
    apparatus = ROOT / "alignrl" / "apparatus"
    files = [*apparatus.glob("families/*.yaml"), *apparatus.glob("instruments/*/*.yaml")]
    assert len(files) >= 12
    for path in files:
        assert path.relative_to(ROOT).as_posix() in names, path


def test_an_unpacked_wheel_aligns_with_a_champion_outside_the_repository(
    wheel: Path, tmp_path: Path
) -> None:
    site = tmp_path / "site"
    zipfile.ZipFile(wheel).extractall(site)
    elsewhere = tmp_path / "elsewhere"  # no repository above: nothing to find by walking up
    elsewhere.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site)}
    env.pop("ALIGNRL_DEBUG", None)

    # One process, as `alignrl` runs: it says where alignrl and its champions were found,
    # then runs the command line's main() (one start of torch instead of two).
    script = (
        "import sys, alignrl, alignrl.runs.sources as s; "
        "print(alignrl.__file__, s.CHAMPIONS, file=sys.stderr); "
        "from alignrl.cli import main; sys.exit(main(sys.argv[1:]))"
    )
    argv = ["align", "--policy", "champion:focus-v1", "--apparatus", "synthetic"]
    argv += ["--seed", "2", "--max-acquisitions", "6", "--json"]
    aligned = subprocess.run(
        [sys.executable, "-c", script, *argv],
        cwd=elsewhere,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert aligned.returncode in (0, 1), aligned.stderr[-3000:]
    module, champions = aligned.stderr.splitlines()[0].split()
    assert Path(module).is_relative_to(site), module  # not the editable checkout
    assert not Path(module).is_relative_to(ROOT)
    assert Path(champions) == site / "alignrl" / "champions"
    result = json.loads(aligned.stdout)
    assert result["policy"] == "mlp-sac" and 0 < result["acquisitions"] <= 6
    assert result["exit_code"] == aligned.returncode
