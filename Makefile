# rainbench: every target builds its own virtual environment on first use.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

# make dataset variables (see README.md)
OUT ?= data
SEED ?=
SKY ?=
LAYOUT ?=
TIME ?=
WEATHER ?=
FRAMES ?= 200
WIDTH ?= 800
HEIGHT ?= 600
RATES ?= 0:100:10
RAIN_MODEL ?= jeon2022
# rain model parameters, NAME=VALUE separated by spaces (docs/rain.md): RAIN_OPTIONS="lens_drops=false"
RAIN_OPTIONS ?=
STORE ?=
SCENES ?= 1
WORKERS ?=
THREADS ?=
# where the per-rate statistics run: auto (a CUDA GPU if torch sees one), cpu, cuda, cuda:N
DEVICE ?=
# OVERWRITE=1: replace a dataset of another config in OUT (generate --overwrite)
OVERWRITE ?=
# make verify: IMAGES=1 also decodes every stored image (verify --images)
IMAGES ?=
# make eval variables
RESULTS ?= results/eval
WEIGHTS ?=
PREDICTIONS ?=
# make eval / make paper: MODEL=REFERENCE pairs of the robustness comparison (docs/models.md)
COMPARE ?=
# make train / make paper variables (docs/models.md)
RECIPE ?= rainbench-yolo11n
TRAIN_OUT ?=
MODELS ?=
PAPER_OUT ?= results/paper

# make scene: where scene.xml goes (default: a folder named by the scene's settings)
SCENE_OUT ?=

# A value as one shell word, whatever it holds (spaces, quotes, $): 'it'\''s'
q = '$(subst ','\'',$(1))'

# None of SEED, SKY, LAYOUT, TIME: the paper's clip (seed 0, cloudy street by day); otherwise
# the seed decides whatever is not given.
SCENE_FLAGS = $(if $(SEED),--seed $(call q,$(SEED)),) $(if $(SKY),--sky $(call q,$(SKY)),) \
	$(if $(LAYOUT),--layout $(call q,$(LAYOUT)),) $(if $(TIME),--time $(call q,$(TIME)),)
# The paper's clip goes to OUT/scene_paper, any other to OUT/scene_<seed>[_<layout>][_<time>][_<sky>]
# (seed 0 when only some of LAYOUT, TIME, SKY are given); another FRAMES, WIDTH or HEIGHT in the
# same folder needs OVERWRITE=1 (the scene is refused, not mixed).
SCENE_NAME = $(if $(SEED)$(SKY)$(LAYOUT)$(TIME),scene_$(or $(SEED),0)$(if $(LAYOUT),_$(LAYOUT))$(if $(TIME),_$(TIME))$(if $(SKY),_$(SKY)),scene_paper)

.PHONY: venv dataset scene verify eval train paper test test-slow bench clean

venv: $(STAMP)

# torch/torchvision are installed first with the exact versions these machines hold on disk.
# pip would compile every installed module to bytecode in one thread; compileall does it over
# every core instead (make venv 156 s -> 131 s on 2 cores, bench/RESULTS.md), and passes over
# what rainbench never imports: packages' own tests, pip, setuptools, Ray's libraries other than
# its core, PyOpenGL's GL bindings (EGL and OSMesa stay): 39 -> 28 s, with imports as fast. Like
# pip, it passes over files that do not compile here (torch ships Python 3.12-only test files).
NOT_COMPILED := /(tests?|pip|setuptools|pygments|_distutils_hack)/|/ray/(rllib|tune|serve|train|data|dashboard|air|llm|workflow|autoscaler)/|/OpenGL/(raw/)?(GL|GLES1|GLES2|GLES3|GLX|WGL|GLU|GLUT|Tk)/
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet --no-compile torch==2.14.1 torchvision==0.29.1
	$(BIN)/pip install --quiet --no-compile -e '.[test,bench,ray]'
	$(BIN)/python -m compileall -q -j 0 -x '$(NOT_COMPILED)' $(VENV)/lib > /dev/null 2>&1 || true
	touch $(STAMP)

dataset: $(STAMP)
	$(if $(filter-out on off,$(WEATHER)),$(error WEATHER: expected on or off (or unset: the rain model decides), got '$(WEATHER)'))
	$(BIN)/rainbench generate --out $(call q,$(OUT)) $(SCENE_FLAGS) --scenes $(call q,$(SCENES)) \
		--frames $(call q,$(FRAMES)) --width $(call q,$(WIDTH)) --height $(call q,$(HEIGHT)) --rates $(call q,$(RATES)) \
		--rain-model $(call q,$(RAIN_MODEL)) $(if $(STORE),--store $(call q,$(STORE)),) \
		$(foreach option,$(RAIN_OPTIONS),--rain-option $(call q,$(option))) \
		$(if $(filter on,$(WEATHER)),--weather-follows-rate,) \
		$(if $(filter off,$(WEATHER)),--no-weather-follows-rate,) \
		$(if $(WORKERS),--workers $(call q,$(WORKERS)),) $(if $(THREADS),--threads $(call q,$(THREADS)),) \
		$(if $(DEVICE),--device $(call q,$(DEVICE)),) \
		$(if $(CLIP_FRAMES),--clip-frames $(call q,$(CLIP_FRAMES)),) \
		$(if $(FIRST_FRAME),--first-frame $(call q,$(FIRST_FRAME)),) $(if $(OVERWRITE),--overwrite,)

eval: $(STAMP)
	$(BIN)/rainbench eval --data $(call q,$(OUT)) --out $(call q,$(RESULTS)) \
		$(foreach w,$(WEIGHTS),--weights $(call q,$(w))) $(if $(PREDICTIONS),--predictions $(call q,$(PREDICTIONS)),) \
		$(foreach c,$(COMPARE),--compare $(call q,$(c)))

# Trains the recipe's model from scratch on clean scenes (resumes a cut-off run when re-run).
train: $(STAMP)
	$(BIN)/rainbench train --recipe $(call q,$(RECIPE)) $(if $(TRAIN_OUT),--out $(call q,$(TRAIN_OUT)),)

# The seed paper's experiment: generate both rain models, evaluate the shipped models, report.
paper: $(STAMP)
	$(BIN)/rainbench paper --out $(call q,$(PAPER_OUT)) --data $(call q,$(OUT)/paper) $(SCENE_FLAGS) --scenes $(call q,$(SCENES)) \
		--frames $(call q,$(FRAMES)) --width $(call q,$(WIDTH)) --height $(call q,$(HEIGHT)) --rates $(call q,$(RATES)) \
		$(foreach m,$(MODELS),--model $(call q,$(m))) $(foreach w,$(WEIGHTS),--weights $(call q,$(w))) \
		$(foreach c,$(COMPARE),--compare $(call q,$(c)))

verify: $(STAMP)
	$(BIN)/rainbench verify $(call q,$(OUT))$(if $(IMAGES), --images)

scene: $(STAMP)
	$(BIN)/rainbench scene $(SCENE_FLAGS) --frames $(call q,$(FRAMES)) \
		--width $(call q,$(WIDTH)) --height $(call q,$(HEIGHT)) \
		--out $(call q,$(or $(SCENE_OUT),$(OUT)/$(SCENE_NAME))) $(if $(OVERWRITE),--overwrite,)

# Two test processes (pytest-xdist), one per core of the 2-core CI machine: 263 s against 435 s
# in one process (bench/RESULTS.md). A test file's tests stay in one process (--dist loadfile),
# so its module fixtures are built once. TEST_WORKERS=0 runs everything in this process.
TEST_WORKERS ?= 2
test: $(STAMP)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# The slow checks, then the fuzzer (tests/test_fuzz.py) with many more random examples than in
# make test (hypothesis profile rainbench-slow).
test-slow: $(STAMP)
	$(BIN)/python -m pytest -q -m slow
	RAINBENCH_HYPOTHESIS_PROFILE=rainbench-slow $(BIN)/python -m pytest -q -p no:cacheprovider tests/test_fuzz.py

bench: $(STAMP)
	mkdir -p results/bench
	$(BIN)/python bench/render.py --json results/bench/render.json
	$(BIN)/python bench/long_clip.py --json results/bench/long_clip.json
	$(BIN)/python bench/rain.py --json results/bench/rain.json
	$(BIN)/python bench/rain_memory.py --json results/bench/rain_memory.json
	$(BIN)/python bench/eval_metrics.py --json results/bench/eval_metrics.json
	$(BIN)/python bench/stats_device.py --json results/bench/stats_device.json
	$(BIN)/python bench/dataset.py --json results/bench/dataset.json
	$(BIN)/python bench/train_reader.py --json results/bench/train_reader.json
	$(BIN)/python bench/inference.py --json results/bench/inference.json
	$(BIN)/python bench/inference.py --imgsz 960 --json results/bench/inference_960.json
	$(BIN)/python bench/inference.py --weights rainbench-yolo11s --imgsz 960 --json results/bench/inference_11s_960.json
	$(BIN)/python bench/backend_agreement.py --data $(OUT)/paper/jeon2022 --json results/bench/backend_agreement.json
	$(BIN)/python bench/quality.py --weights rainbench-yolo11n --weights rainbench-yolo11s \
		--layouts street,intersection,curved,highway,residential --json results/bench/quality.json

clean:
	rm -rf $(VENV) build *.egg-info
