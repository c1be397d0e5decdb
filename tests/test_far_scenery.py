"""Geoms no pixel can come from (out of view, of the mirror's view and of the sun's shadow box:
FrameRenderer.hidden_geoms) are left out of every pass without changing a byte; a renderer
leaves its model in the base weather."""

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


def _same_with_every_geom_drawn(monkeypatch, config):
    """Render ``config`` leaving out the hidden geoms, then drawing every geom: the same images;
    returns the fewest geoms left out of a pass."""
    setup = build_scene(config)
    weathers = sweep_weathers(config, setup.layout)
    left_out = []
    hidden = gr.FrameRenderer.hidden_geoms
    monkeypatch.setattr(gr.FrameRenderer, "hidden_geoms",
                        lambda self, *args: left_out.append(int(hidden(self, *args).sum()))
                        or hidden(self, *args))
    culled = _frames(config, setup, weathers)
    monkeypatch.setattr(gr.FrameRenderer, "hidden_geoms",
                        lambda self, *args: np.zeros(self.model.ngeom, bool))
    drawn = _frames(config, setup, weathers)
    for ours, theirs in zip(culled, drawn):
        for image, reference in zip(ours, theirs):
            assert np.array_equal(image, reference, equal_nan=True)
    return min(left_out), setup.model.ngeom


@pytest.mark.parametrize("sky, time_of_day", [("clear", "day"), ("cloudy", "night")])
def test_far_scenery_is_left_out_with_the_same_bytes(monkeypatch, sky, time_of_day):
    """The last frame of a 5-minute highway clip (7 km of road): the sun's shadows, the wet
    road's mirror and the puddles (physical rain, the weather following the rate), the lamps at
    night; most geoms are left out of every pass and every image is the same."""
    config = GenerateConfig(frames=1, frame_offset=2999, seed=3, layout="highway", sky=sky,
                            time_of_day=time_of_day, width=160, height=120,
                            rates=(0.0, 25.0, 100.0), rain_model="physical")
    fewest, ngeom = _same_with_every_geom_drawn(monkeypatch, config)
    assert fewest > 0.8 * ngeom


@pytest.mark.parametrize("layout, time_of_day, size", [
    ("street", "day", (160, 120)), ("intersection", "dusk", (160, 120)),
    ("residential", "day", (160, 120)),
    # the mirror pass renders at half size, rounded: 14 x 8, wider than the image's 27 x 17
    ("highway", "day", (27, 17))])
def test_geoms_out_of_view_are_left_out_with_the_same_bytes(monkeypatch, layout, time_of_day, size):
    """Frames of 20 s clips under a clear sky (the sun casts shadows; at dusk a low sun, long
    shadows, the lamps), physical rain with the weather following the rate: the geoms behind
    the camera and beside its view, outside the sun's shadow box and out of the mirror's view,
    are left out of every pass, and every image is the same."""
    config = GenerateConfig(frames=2, frame_offset=60, seed=2, layout=layout, sky="clear",
                            time_of_day=time_of_day, width=size[0], height=size[1],
                            rates=(0.0, 30.0, 100.0), rain_model="physical")
    fewest, _ = _same_with_every_geom_drawn(monkeypatch, config)
    assert fewest > 0


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
