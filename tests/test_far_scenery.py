"""A long clip's far scenery is left out of every pass (FrameRenderer.beyond_reach) without
changing a byte; a renderer leaves its model in the base weather."""

import numpy as np
import pytest

from rainbench.gen import render as gr
from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import build_scene, render_clip, sweep_weathers


def _frames(config, setup, weathers):
    """Every image of the clip: clean RGB, ids, depth, each weather's re-render, boxes."""
    out = []
    for _, frame, _ in render_clip(config, setup, weathers, depth=True):
        out.append([frame.rgb.copy(), frame.instance.copy(), frame.depth.copy(),
                    frame.labels.bbox.copy(), *(frame.weather_rgb(w).copy() for w in weathers)])
    return out


@pytest.mark.parametrize("sky, time_of_day", [("clear", "day"), ("cloudy", "night")])
def test_far_scenery_is_left_out_with_the_same_bytes(monkeypatch, sky, time_of_day):
    """The last frame of a 5-minute highway clip (7 km of road, thousands of geoms more than
    2 km away): the sun's shadows, the wet road's mirror and the puddles (physical rain, the
    weather following the rate), the lamps at night; every image is the same with the far
    geoms drawn."""
    config = GenerateConfig(frames=1, frame_offset=2999, seed=3, layout="highway", sky=sky,
                            time_of_day=time_of_day, width=160, height=120,
                            rates=(0.0, 25.0, 100.0), rain_model="physical")
    setup = build_scene(config)
    weathers = sweep_weathers(config, setup.layout)
    left_out = []
    reach = gr.FrameRenderer.beyond_reach
    monkeypatch.setattr(gr.FrameRenderer, "beyond_reach",
                        lambda self, data: left_out.append(int(reach(self, data).sum()))
                        or reach(self, data))
    culled = _frames(config, setup, weathers)
    assert min(left_out) > setup.model.ngeom // 2  # most of the scene is far away
    monkeypatch.setattr(gr.FrameRenderer, "beyond_reach",
                        lambda self, data: np.zeros(self.model.ngeom, bool))
    drawn = _frames(config, setup, weathers)
    for ours, theirs in zip(culled[0], drawn[0]):
        assert np.array_equal(ours, theirs, equal_nan=True)


def test_nothing_is_beyond_reach_in_the_paper_clip(monkeypatch):
    """A 20 s clip's scene is within reach everywhere: its passes are what they always were."""
    config = GenerateConfig(frames=1, frame_offset=199, width=160, height=120,
                            rates=(0.0,), rain_model="jeon2022")
    seen = []
    reach = gr.FrameRenderer.beyond_reach
    monkeypatch.setattr(gr.FrameRenderer, "beyond_reach",
                        lambda self, data: seen.append(reach(self, data).any()) or reach(self, data))
    _frames(config, build_scene(config), ())
    assert seen and not any(seen)


def test_a_clip_rendered_again_on_the_same_scene_is_the_same():
    """A renderer writes each weather into the model; closed, it puts the base weather back, so
    a second render of the same SceneSetup (here after 100 mm/h with the vehicles' lamps lit)
    gives the first one's bytes."""
    config = GenerateConfig(frames=1, frame_offset=100, seed=3, layout="highway", sky="clear",
                            time_of_day="day", width=160, height=120, rates=(0.0, 100.0),
                            rain_model="physical")
    setup = build_scene(config)
    weathers = sweep_weathers(config, setup.layout)
    first = _frames(config, setup, weathers)
    again = _frames(config, setup, weathers)
    for ours, theirs in zip(first[0], again[0]):
        assert np.array_equal(ours, theirs, equal_nan=True)
