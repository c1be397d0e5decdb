"""Rain on a real rendered frame: SSIM falls monotonically with rate, for both models."""

from rainbench.gl import mujoco  # imported once the GL backend is chosen
import numpy as np
import pytest

from rainbench import rain
from rainbench.gen import sim
from rainbench.gen.config import GenerateConfig
from rainbench.gen.generate import build_scene
from rainbench.gen.render import FrameRenderer

RATES = [10.0, 20.0, 40.0, 60.0, 80.0, 100.0]


@pytest.fixture(scope="module")
def rendered_frame():
    config = GenerateConfig(seed=2, width=320, height=240)
    setup = build_scene(config)
    data = mujoco.MjData(setup.model)
    sim.advance(setup.model, data, sim.ActorDriver(setup.model, setup.layout), 0.0, 6.0)
    with FrameRenderer(setup.model, 320, 240, setup.geom_instance) as renderer:
        renderer.update(data)
        rgb, depth = renderer.render_rgb_depth()
        _, geometry = renderer.render_instances()
        depth[~geometry] = np.inf
        return rgb, depth, renderer.K


@pytest.mark.parametrize("model", rain.RAIN_MODELS)
def test_mean_ssim_decreases_with_rate(rendered_frame, model):
    rgb, depth, K = rendered_frame
    ssims = []
    for frame_index in range(3):
        seeds = np.random.SeedSequence([0, 2, frame_index])
        frames = rain.render_rain_sweep(rgb, depth, RATES, config=rain.RainConfig(model=model),
                                        K=K, seed_sequence=seeds)
        ssims.append([rain.image_quality(rgb, frame.rgb)[0] for frame in frames])
    mean_ssim = np.mean(ssims, axis=0)
    assert (np.diff(mean_ssim) < 0).all(), mean_ssim
    assert mean_ssim[0] < 1.0
