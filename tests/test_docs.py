"""The runnable examples of docs/reading.md run on a small dataset."""

import re
from pathlib import Path

import pytest

from rainbench.gen.config import DatasetConfig
from rainbench.gen.dataset import run_dataset

DOCS = Path(__file__).resolve().parents[1] / "docs"


@pytest.mark.parametrize("index", [0, 1, 2, 3])
def test_reading_examples_run(tmp_path, index, monkeypatch, capsys):
    blocks = re.findall(r"```python\n(.*?)```", (DOCS / "reading.md").read_text(), re.S)
    assert len(blocks) == 4
    run_dataset(DatasetConfig(frames=2, width=96, height=72, rates=(0.0, 50.0)), tmp_path / "data")
    monkeypatch.chdir(tmp_path)
    exec(compile(blocks[index], f"docs/reading.md block {index}", "exec"), {})
    if index < 3:
        assert capsys.readouterr().out.strip()
