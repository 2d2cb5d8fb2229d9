# DrivingScene: `make run` (set up, then the viewer on the demo scene) and `make test`.
SHELL := /bin/bash
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
# A CPU build of torch (installed from local disk on our machines); override for a CUDA build.
TORCH_SPEC ?= torch==2.13.0
STAMP := $(VENV)/.installed
OUT ?= out

.PHONY: setup run test lint clean-venv real-data benchmark views still-ego

setup: $(STAMP)

$(STAMP): pyproject.toml .ci/install-system-deps.sh
	./.ci/install-system-deps.sh
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip 2>/dev/null || true
	$(PY) -m pip install -q "$(TORCH_SPEC)"
	$(PY) -m pip install -q -e ".[dev,nuscenes,viewer]"
# nuscenes-devkit without its deps: its pins (numpy<2, opencv-python-headless) would replace numpy 2
# and clash with opencv-contrib's cv2; the [nuscenes] extra holds what its code imports (pyproject.toml)
	$(PY) -m pip install -q --no-deps "nuscenes-devkit==1.2.0"
	touch $@

# With a display: the viewer window on the bundled demo scene. Without one: the same viewer renders
# every rig camera at three times (and a PLY) to $(OUT)/view through EGL, then exits.
run: setup
	@if [ -n "$$DISPLAY" ]; then $(VENV)/bin/drivingscene-view; \
	else $(VENV)/bin/drivingscene-view --headless --out $(OUT)/view --force; fi

test: setup
	$(PY) -m pytest -q -p no:cacheprovider

lint: setup
	$(VENV)/bin/ruff check app drivingscene tests

clean-venv:
	rm -rf $(VENV)

# The model on the real DDAD development scene (../shared/real, never copied into the repo):
# import the pairs 0->1, 1->2 and 0->2 (sample 1 held out as the real in-between frame), then
# score them into docs/real-data.md. Needs the scene at $(REAL). The side-by-side figures show real
# frames: they go to $(OUT)/real-data (not committed; the data is not ours to redistribute).
REAL ?= ../shared/real/ddad_scene_02
REAL_OUT ?= data/real
# Refinement rows (docs/refinement.md): budgets in seconds, and again fitting half of the LiDAR.
REAL_REFINE ?= --refine 10 30 --lidar
real-data: setup
	$(VENV)/bin/drivingscene import ddad $(REAL) --samples 0 1 -o $(REAL_OUT)/ddad02_0-1.npz --force
	$(VENV)/bin/drivingscene import ddad $(REAL) --samples 1 2 -o $(REAL_OUT)/ddad02_1-2.npz --force
	$(VENV)/bin/drivingscene import ddad $(REAL) --samples 0 2 --eval 1 -o $(REAL_OUT)/ddad02_0-2.npz --force
	$(VENV)/bin/drivingscene import ddad $(REAL) --samples 0 0 -o $(REAL_OUT)/ddad02_0-0.npz --force
	$(VENV)/bin/drivingscene bench real --force $(REAL_OUT)/ddad02_0-1.npz $(REAL_OUT)/ddad02_1-2.npz $(REAL_OUT)/ddad02_0-2.npz \
		$(REAL_OUT)/ddad02_0-0.npz \
		--names "DDAD scene_02, 0->1" "DDAD scene_02, 1->2" "DDAD scene_02, 0->2 (1 held out)" \
		"DDAD scene_02, 0->0 (sample 0 twice: no parallax over time)" \
		--notes docs/real-data-notes.md --out docs/real-data.md --json docs/real-data.json --images $(OUT)/real-data $(REAL_REFINE)

# The whole benchmark (docs/benchmark.md, docs/benchmark.json, docs/images/benchmark_*.png): every
# method at its settings on generated procedural test pairs and on the real DDAD pair (import it
# first: `make real-data`), stability sweeps, parsimony, ablations. About 30-45 minutes on 2 cores.
# The single-stage ablation needs a joint run and its two-stage pair (docs/benchmark-notes.md).
ABLATION_RUNS := $(wildcard runs/dynamic-match4/model.safetensors)
BENCH_ABLATION ?= $(if $(ABLATION_RUNS),--two-stage-weights runs/dynamic-match4/model.safetensors \
	$(if $(wildcard runs/joint-match4/model.safetensors),--joint-weights runs/joint-match4/model.safetensors,) \
	$(if $(wildcard runs/dynamic-nowarp4/model.safetensors),--no-warp-weights runs/dynamic-nowarp4/model.safetensors,),)
# Network width against quality and speed: the two width runs of docs/training-notes.md, when present.
WIDTH_RUNS := $(wildcard runs/width16/model.safetensors runs/width32/model.safetensors)
BENCH_WIDTHS ?= $(if $(WIDTH_RUNS),--width-weights $(WIDTH_RUNS),)
# Without those runs (they are not in the repository), the ablation models' points and the widths of
# the run that scored them (2026-11-26, kept as docs/benchmark-ablation-models.json) are carried over,
# marked as that run's.
BENCH_CARRY ?= $(if $(ABLATION_RUNS)$(WIDTH_RUNS),,--carry-from docs/benchmark-ablation-models.json)
benchmark: setup
	$(VENV)/bin/drivingscene bench report --force --scenes $(REAL_OUT)/ddad02_0-2.npz --names "DDAD scene_02, 0->2 (1 held out)" \
		$(BENCH_ABLATION) $(BENCH_WIDTHS) $(BENCH_CARRY) --notes docs/benchmark-notes.md --out docs/benchmark.md --json docs/benchmark.json --charts docs/images

# Where the viewer's user looks (docs/magnification.md): the approaches to views larger than the
# input (bench magnify, procedural test pairs and the real DDAD pair: import it first, `make
# real-data`), and every method from viewpoints away from the rig against procedural ground truth
# (bench views into docs/views; the real pair's magnification and overview pictures go to
# $(OUT)/views-real: real frames are never committed). About 45 minutes on 2 cores.
views: setup
	$(VENV)/bin/drivingscene bench magnify --force --count 4 --scenes $(REAL_OUT)/ddad02_0-2.npz \
		--out docs/magnification-bench.md --json docs/magnification-bench.json
	$(VENV)/bin/drivingscene bench magnify --force --default-only --count 4 --scenes $(REAL_OUT)/ddad02_0-2.npz \
		--out docs/magnification-default.md --json docs/magnification-default.json
	$(VENV)/bin/drivingscene bench views --force --count 4 --out docs/views
	$(VENV)/bin/drivingscene bench views --force --count 1 --scenes $(REAL_OUT)/ddad02_0-2.npz --out $(OUT)/views-real

# A stopped ego (docs/still-ego.md): procedural test pairs at ego speed 0, with the usual moving
# objects and with none, scored like the real pairs, the in-between frame against blending the
# keyframes (issue 45: no worse than it minus 1 dB). The images carry a camera's sensor noise
# (STILL_NOISE, about 2.5 grey levels): without any, a blend where nothing moved is bit-exact. One
# pair where nothing moves at half that noise and one without noise show where the floor stops holding.
STILL_OUT ?= data
STILL_NOISE := 0.01
STILL_NAMES := $(foreach s,200000 200001 200002 200003,"still ego, moving objects $(s)") \
	$(foreach s,200000 200001 200002 200003,"still ego, nothing moves $(s)") \
	"still ego, nothing moves 200000, noise 0.005" "still ego, nothing moves 200000, no noise"
STILL_SYNTH := $(VENV)/bin/drivingscene synth --split test --ego-speed 0 --force --no-progress
still-ego: setup
	$(STILL_SYNTH) --count 4 --noise-std $(STILL_NOISE) -o $(STILL_OUT)/still176/moving
	$(STILL_SYNTH) --count 4 --noise-std $(STILL_NOISE) --num-moving 0 -o $(STILL_OUT)/still176/static
	$(STILL_SYNTH) --count 1 --noise-std 0.005 --num-moving 0 -o $(STILL_OUT)/still176/static_noise_half
	$(STILL_SYNTH) --count 1 --num-moving 0 -o $(STILL_OUT)/still176/static_no_noise
	$(VENV)/bin/drivingscene bench real --force $(STILL_OUT)/still176/moving/pair_*.npz $(STILL_OUT)/still176/static/pair_*.npz \
		$(STILL_OUT)/still176/static_noise_half/pair_200000.npz $(STILL_OUT)/still176/static_no_noise/pair_200000.npz \
		--names $(STILL_NAMES) --title "DrivingScene with the ego standing still (procedural pairs)" --notes docs/still-ego-notes.md --out docs/still-ego.md --json docs/still-ego.json
