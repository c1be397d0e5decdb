"""Rain for rainbench: two rain models, lens water, image-quality statistics (rates in mm/h are
parsed and named by :mod:`rainbench.store.rates`).

Pure numpy/OpenCV; no MuJoCo. Models (docs/rain.md):

* ``jeon2022`` (default): the seed paper's eq. 5 drop count, drawn as water drops on the lens.
* ``physical``: Marshall-Palmer falling drops drawn as streaks, extinction and airlight from the
  depth render, optional lens drops.

Typical use::

    frame = render_rain(rgb, depth, 50.0, config=RainConfig(), K=K,
                        seed_sequence=np.random.SeedSequence([rain_seed, scene_seed, frame_index]),
                        lens_clock=LensClock(np.random.SeedSequence([rain_seed, scene_seed]), frame_index, fps))
"""

from rainbench.rain.config import RAIN_MODELS, RainConfig
from rainbench.rain.lens import LensClock, LensDrops, jeon2022_drop_count
from rainbench.rain.metrics import BoxRainReference, SsimReference, box_rain_labels, image_quality, luma, psnr, ssim_gray
from rainbench.rain.physical import AirDrops, extinction_coefficient, marshall_palmer_slope, terminal_velocity, visibility_km
from rainbench.rain.render import Drops, RainFrame, render_rain, render_rain_sweep, sample_drops

__all__ = [
    "RAIN_MODELS",
    "AirDrops",
    "BoxRainReference",
    "Drops",
    "LensClock",
    "LensDrops",
    "RainConfig",
    "RainFrame",
    "SsimReference",
    "box_rain_labels",
    "extinction_coefficient",
    "image_quality",
    "jeon2022_drop_count",
    "luma",
    "marshall_palmer_slope",
    "psnr",
    "render_rain",
    "render_rain_sweep",
    "sample_drops",
    "ssim_gray",
    "terminal_velocity",
    "visibility_km",
]
