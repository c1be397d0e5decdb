"""The runnable examples of docs/reading.md run on a small dataset; the scripts that draw the
docs' images run."""

import importlib.util
import re
from pathlib import Path

import numpy as np
import pytest

from rainbench.gen.config import DatasetConfig
from rainbench.gen.dataset import run_dataset

DOCS = Path(__file__).resolve().parents[1] / "docs"


@pytest.fixture(scope="module")
def reading_data(tmp_path_factory):
    """2 frames at 96x72, 0 and 50 mm/h, of the residential street by day: its parked cars are
    near enough to be labels at that size (the paper's street has none there)."""
    root = tmp_path_factory.mktemp("reading")
    run_dataset(DatasetConfig(frames=2, width=96, height=72, rates=(0.0, 50.0), layout="residential",
                              time_of_day="day"), root / "data")
    return root


@pytest.mark.parametrize("index", [0, 1, 2, 3])
def test_reading_examples_run(reading_data, index, monkeypatch, capsys):
    blocks = re.findall(r"```python\n(.*?)```", (DOCS / "reading.md").read_text(), re.S)
    assert len(blocks) == 4
    monkeypatch.chdir(reading_data)
    names = {}
    exec(compile(blocks[index], f"docs/reading.md block {index}", "exec"), names)
    lines = capsys.readouterr().out.strip().splitlines()
    if index == 0:  # the 4 images (2 frames x 2 rates) in one batch, labelled boxes
        assert lines[0].startswith("torch.Size([4, 3, 72, 96]) torch.Size([") and len(lines) == 1
    elif index == 1:  # cars at 50 mm/h
        assert lines[0].startswith("2 (72, 96, 3) [[") and names["target"]["boxes"].shape[0] > 0
        assert set(names["target"]["labels"].tolist()) == {2}
    elif index == 2:
        assert len(lines) == 2 and all("(72, 96, 3)" in line for line in lines)
        assert sum(int(re.search(r"\((\d+), 4\)", line).group(1)) for line in lines) > 0
    else:
        assert names["image"].shape == (72, 96, 3) and names["boxes"].shape[1:] == (4,)
        assert len(names["boxes"]) == len(names["classes"]) > 0


def _docs_script(name):
    spec = importlib.util.spec_from_file_location(name, DOCS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_scenes_montage_script_draws_labelled_tiles(monkeypatch):
    script = _docs_script("scenes_montage")
    monkeypatch.setattr(script, "SEEDS", (2, 3, 4, 8))
    monkeypatch.setattr(script, "WIDTH", 160)
    monkeypatch.setattr(script, "HEIGHT", 120)
    monkeypatch.setattr(script, "TILE", (160, 120))
    labels = []
    put_text = script.cv2.putText
    monkeypatch.setattr(script.cv2, "putText", lambda image, text, *args, **kwargs: (
        labels.append(text), put_text(image, text, *args, **kwargs))[1])
    image = script.montage()
    assert image.shape == (120, 640, 3) and image.dtype == np.uint8
    tiles = [image[:, 160 * k:160 * (k + 1)] for k in range(4)]
    assert len({tile.tobytes() for tile in tiles}) == 4
    # each tile names its seed and what the seed drew (seed 2: the street at night)
    assert [label.split(":")[0] for label in labels] == ["seed 2", "seed 3", "seed 4", "seed 8"]
    assert labels[0].endswith("night") and "street" in labels[0]
    monkeypatch.setattr(script, "SEEDS", (2, 3))
    with pytest.raises(ValueError, match="SEEDS: expected a multiple of 4 seeds, got 2"):
        script.montage()


def test_time_of_day_script_draws_day_dusk_and_night(monkeypatch):
    script = _docs_script("time_of_day")
    monkeypatch.setattr(script, "WIDTH", 160)
    monkeypatch.setattr(script, "HEIGHT", 120)
    image = script.montage()
    assert image.shape == (120, 240, 3)
    luma = [image[60 * row + 25:60 * (row + 1), 80 * col:80 * (col + 1)].mean()
            for row in range(2) for col in range(3)]  # below the labels
    day, dusk, night = luma[:3]
    assert day > dusk > night  # the top row at 0 mm/h
    assert luma[3] < day  # rain darkens the day


def _rain_parameter_rows() -> dict[str, str]:
    """docs/rain.md's RainConfig table as {field: default cell}, a row naming several fields
    split over their comma-separated defaults."""
    text = (DOCS / "rain.md").read_text()
    table = text[text.index("## Parameters (`RainConfig`)"):]
    table = table[:table.index("\n## ")]
    rows = {}
    for line in table.splitlines():
        cells = [cell.strip() for cell in line.strip().strip("|").split("|")]
        names = re.findall(r"`(\w+)`", cells[0]) if len(cells) >= 3 else []
        if not names or cells[0] == "field":
            continue
        values = [value.strip() for value in cells[1].split(",")] if len(names) > 1 else [cells[1]]
        assert len(values) == len(names), f"docs/rain.md row {cells[0]}: {len(names)} fields, defaults {cells[1]!r}"
        rows.update(zip(names, values))
    return rows


def test_rain_parameter_table_lists_every_rain_config_field_with_its_default():
    import dataclasses

    from rainbench.rain import RainConfig

    rows = _rain_parameter_rows()
    fields = {field.name: field.default for field in dataclasses.fields(RainConfig)}
    assert sorted(rows) == sorted(fields), "docs/rain.md's RainConfig table and RainConfig's fields differ"
    for name, default in fields.items():
        documented = rows[name].strip("`")
        if isinstance(default, bool) or default is None or isinstance(default, str):
            assert documented.strip('"') == str(default), (name, documented, default)
        else:
            assert float(documented) == float(default), (name, documented, default)


def test_rain_api_imports_run_as_documented():
    text = (DOCS / "rain.md").read_text()
    block = text[text.index("## API"):]
    block = block[block.index("```python") + len("```python"):block.index("```", block.index("```python") + 9)]
    imports = re.findall(r"^from [\w.]+ import (?:\([^)]*\)|[^\n]*)", block, flags=re.MULTILINE)
    assert imports, "docs/rain.md's API block has no import"
    exec("\n".join(imports), {})  # an ImportError names the missing name
