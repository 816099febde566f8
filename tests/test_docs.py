"""The README's examples run as written: every bash block (but the two set-up commands, which
CI runs itself) and the Python block, in an empty folder, with the installed package."""
import re
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks(lang: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", README.read_text(), flags=re.S)


def _example_shell_blocks() -> list[str]:
    return [b for b in _blocks("bash") if "python -m venv" not in b]


def test_the_readme_has_its_examples():
    assert len(_blocks("python")) == 1 and len(_example_shell_blocks()) == 2


@pytest.mark.slow
@pytest.mark.parametrize("k", range(2))
def test_readme_shell_block_runs_as_pasted(k, tmp_path):
    block = _example_shell_blocks()[k]
    bin_dir = Path(sys.executable).parent
    r = subprocess.run(["bash", "-euo", "pipefail", "-c", block], cwd=tmp_path,
                       capture_output=True, text=True, timeout=280,
                       env={"PATH": f"{bin_dir}:/usr/bin:/bin", "HOME": str(tmp_path)})
    assert r.returncode == 0, f"block {k} failed:\n{block}\n--- stderr:\n{r.stderr[-3000:]}"
    outputs = re.findall(r"-o (\S+\.(?:parquet|toml))", block)
    for name in outputs:
        assert (tmp_path / name).is_file(), f"{name} not written by block {k}"


@pytest.mark.slow
def test_readme_python_block_runs(tmp_path):
    r = subprocess.run([sys.executable, "-c", _blocks("python")[0]], cwd=tmp_path,
                       capture_output=True, text=True, timeout=280)
    assert r.returncode == 0, r.stderr[-3000:]
    lines = [line.strip() for line in r.stdout.strip().splitlines()]
    assert float(lines[0]) > 0                               # a validation error in nm
    header = next(i for i, line in enumerate(lines) if line.split()[:1] == ["effect"])
    first = lines[header + 1]                                # the row after the index name
    assert first.split()[0] == "magnetic_force", r.stdout    # the hidden effect ranks first
