# Denoiser training-data pipeline. `make dataset` and `make test` set themselves up.
SHELL := /bin/bash
PY := .venv/bin/python
CONFIG ?= configs/default.yaml
OUT ?=
SCHEDULER ?=
WORKERS ?=
export DENOISE_DATA ?= $(CURDIR)/data
# test processes (pytest-xdist): one a core, at most 4 (each loads torch and Mitsuba); TEST_JOBS=0 runs in one process
TEST_JOBS ?= $(shell n=$$(nproc 2>/dev/null || echo 2); echo $$(( n < 4 ? n : 4 )))

.PHONY: setup dataset estimate test bench train report compare compare-realtime compare-temporal compare-nppd scaling hard-cases real-scenes chaos preview contact-sheet clean-data help

help:            ## list targets
	@grep -E '^[a-z-]+:.*##' $(MAKEFILE_LIST) | sed 's/:.*##/\t/'

setup:           ## create .venv, install dependencies (CPU torch without a GPU) and libLLVM >= 16
	@bash scripts/setup.sh

dataset: setup   ## build the dataset of CONFIG (default: configs/default.yaml) on a LocalCluster or SCHEDULER
	$(PY) -m pipeline dataset --config $(CONFIG) $(if $(OUT),--out $(OUT)) $(if $(SCHEDULER),--scheduler $(SCHEDULER)) $(if $(WORKERS),--workers $(WORKERS))

test: setup      ## the whole test suite (TEST_JOBS processes)
	$(PY) -m pytest -q -n $(TEST_JOBS) --dist loadgroup tests

estimate: setup  ## predict samples, core-hours, store bytes and wall time of CONFIG on WORKERS workers
	$(PY) -m pipeline estimate --config $(CONFIG) $(if $(WORKERS),--workers $(WORKERS))

bench: setup     ## benchmarks that print figures: rendering, store, scheduler, then every model through torch.compile
	$(PY) -m pipeline bench
	$(PY) -m training bench --compile

# The first model: nbg (1 spp) beats its own noisy input on the default store's test split in seconds; the layer
# family needs make compare's budget to beat its 8-spp input (docs/real-scenes.md, "The first model")
train: setup     ## train MODEL (default nbg) on STORE (default data/default.zarr) for STEPS (default 1000)
	$(PY) -m training train --model $(or $(MODEL),nbg) --store $(or $(STORE),data/default.zarr) --out $(or $(RUN),data/runs/$(or $(MODEL),nbg)) $(if $(STEPS),--steps $(STEPS))

report: setup    ## evaluate RUNS on STORE and write a report
	$(PY) -m training report --runs $(or $(RUNS),data/runs/*) --store $(or $(STORE),data/default.zarr) --out $(or $(REPORT),data/report)

COMPARE_MODELS ?= layer pixelgather layer-optimized samplesplat
COMPARE_STEPS ?= 800
REALTIME_MODELS ?= nbg wskpn unet
REALTIME_STEPS ?= 10000
# SEEDS=N trains the layer-family and real-time models with seeds 0..N-1 (seed 0 in data/runs/MODEL, seed s
# in data/runs/MODEL-seedS); the report gives their spread. The temporal models (hours each) train once.
SEEDS ?= 1
SEED_LIST := $(shell seq 0 $$(( $(SEEDS) - 1 )))
seed_runs = $(foreach m,$(1),$(foreach s,$(SEED_LIST),data/runs/$(m)$(if $(filter-out 0,$(s)),-seed$(s))))
COMPARE_START := $(shell date +%s)
compare: setup   ## every denoiser family, OIDN and the inputs on the same held-out scenes, clips and hard cases: one report (hours; SEEDS=N repeats the non-temporal models)
	$(PY) -m pipeline dataset --config configs/train-cpu.yaml --out data/train-cpu.zarr
	$(PY) -m pipeline dataset --config configs/eval-cpu.yaml --out data/eval-cpu.zarr
	for m in $(COMPARE_MODELS); do for s in $(SEED_LIST); do \
	  $(PY) -m training train --model $$m --store data/train-cpu.zarr --steps $(COMPARE_STEPS) --crop 64 --seed $$s \
	    --out data/runs/$$m$$( [ $$s = 0 ] || echo -seed$$s ) || exit 1; \
	done; done
	$(MAKE) --no-print-directory compare-realtime REALTIME_REPORT=0
	$(MAKE) --no-print-directory compare-temporal TEMPORAL_REPORT=0
	$(PY) -m pipeline dataset --config configs/hard-cases.yaml --out data/hard-cases.zarr
	$(PY) -m training report --runs $(call seed_runs,$(COMPARE_MODELS) $(REALTIME_MODELS)) \
	  $(addprefix data/runs-temporal/,$(TEMPORAL_MODELS)) --store data/eval-cpu.zarr \
	  --clips-store data/eval-temporal-cpu.zarr --hard-cases data/hard-cases.zarr --out data/report-compare
	@echo "make compare: data/report-compare/report.md in $$(( $$(date +%s) - $(COMPARE_START) )) s"

REALTIME_REPORT ?= 1
compare-realtime: setup ## the 1-spp part of the comparison: nbg, wskpn and unet (OIDN's architecture) on train-cpu, report on eval-cpu (minutes)
	$(PY) -m pipeline dataset --config configs/train-cpu.yaml --out data/train-cpu.zarr
	$(PY) -m pipeline dataset --config configs/eval-cpu.yaml --out data/eval-cpu.zarr
	for m in $(REALTIME_MODELS); do for s in $(SEED_LIST); do \
	  $(PY) -m training train --model $$m --store data/train-cpu.zarr --steps $(REALTIME_STEPS) --crop 64 --seed $$s \
	    --out data/runs/$$m$$( [ $$s = 0 ] || echo -seed$$s ) || exit 1; \
	done; done
	if [ "$(REALTIME_REPORT)" = 1 ]; then \
	  $(PY) -m training report --runs $(call seed_runs,$(REALTIME_MODELS)) --store data/eval-cpu.zarr --out data/report-realtime; \
	fi

TEMPORAL_MODELS ?= temporal temporal-uniform temporal-perframe
TEMPORAL_STEPS ?= 1500
TEMPORAL_CROP ?= 64
TEMPORAL_CFG ?= {"size": "small"}
TEMPORAL_REPORT ?= 1
compare-temporal: setup ## adaptive vs uniform vs per-frame at 4 spp on 12 held-out moving clips (train- and eval-temporal-cpu; hours on a CPU)
	$(PY) -m pipeline dataset --config configs/train-temporal-cpu.yaml --out data/train-temporal-cpu.zarr
	$(PY) -m pipeline dataset --config configs/eval-temporal-cpu.yaml --out data/eval-temporal-cpu.zarr
	for m in $(TEMPORAL_MODELS); do \
	  $(PY) -m training train --model $$m --store data/train-temporal-cpu.zarr --steps $(TEMPORAL_STEPS) \
	    --crop $(TEMPORAL_CROP) --model-cfg '$(TEMPORAL_CFG)' --out data/runs-temporal/$$m || exit 1; \
	done
	if [ "$(TEMPORAL_REPORT)" = 1 ]; then \
	  $(PY) -m training report --runs $(addprefix data/runs-temporal/,$(TEMPORAL_MODELS)) \
	    --store data/eval-temporal-cpu.zarr --out data/report-temporal; \
	fi

NPPD_SPPS ?= 2 4 8
NPPD_STEPS ?= 500
NPPD_CROP ?= 64
NPPD_CFG ?= {"size": "small"}
# 1e-3, not the paper's 1e-4: at 500 steps it scored +0.14 to +0.68 dB PSNR higher (docs/training.md)
NPPD_LR ?= 1e-3
compare-nppd: setup ## nppd beside layer, temporal (if trained) and OIDN at 2, 4 and 8 spp on 12 held-out moving clips (about 1.5 hours on a CPU)
	$(PY) -m pipeline dataset --config configs/train-temporal-cpu.yaml --out data/train-temporal-cpu.zarr
	$(PY) -m pipeline dataset --config configs/eval-temporal-cpu.yaml --out data/eval-temporal-cpu.zarr
	for s in $(NPPD_SPPS); do \
	  $(PY) -m training train --model nppd --store data/train-temporal-cpu.zarr --steps $(NPPD_STEPS) --spp $$s \
	    --crop $(NPPD_CROP) --lr $(NPPD_LR) --model-cfg '$(NPPD_CFG)' --out data/runs-nppd/nppd-$${s}spp || exit 1; \
	  $(PY) -m training train --model layer --store data/train-temporal-cpu.zarr --steps $(NPPD_STEPS) --spp $$s \
	    --crop $(NPPD_CROP) --out data/runs-nppd/layer-$${s}spp || exit 1; \
	  extra=; if [ $$s = 4 ] && [ -f data/runs-temporal/temporal/checkpoint.pt ]; then extra=data/runs-temporal/temporal; fi; \
	  $(PY) -m training report --runs data/runs-nppd/nppd-$${s}spp data/runs-nppd/layer-$${s}spp $$extra \
	    --store data/eval-temporal-cpu.zarr --out data/report-nppd-$${s}spp --baseline nppd-$${s}spp || exit 1; \
	done

SCALING_CONFIG ?= configs/scaling-cpu.yaml
scaling: setup   ## what the data buys: quality against training frames and scene variety, with fits (configs/scaling-cpu.yaml: about 2.5 hours on 2 cores; resumes; TARGET_RELMSE=X TARGET_PSNR=Y; STUDY_MODELS=nbg,wskpn: only those models' runs)
	$(PY) -m studies scaling --config $(SCALING_CONFIG) $(if $(OUT),--out $(OUT)) $(if $(WORKERS),--workers $(WORKERS)) \
	  $(if $(STUDY_MODELS),--models $(STUDY_MODELS)) \
	  $(if $(TARGET_RELMSE),--target-relmse $(TARGET_RELMSE)) $(if $(TARGET_PSNR),--target-psnr $(TARGET_PSNR))

HARD_RUNS ?= $(wildcard data/runs/*/checkpoint.pt data/runs-temporal/*/checkpoint.pt)
hard-cases: setup ## render configs/hard-cases.yaml, then evaluate RUNS (default: every trained run), OIDN and the input per case
	$(PY) -m pipeline dataset --config configs/hard-cases.yaml --out data/hard-cases.zarr
	$(PY) -m training hard-cases --store data/hard-cases.zarr --runs $(or $(RUNS),$(dir $(HARD_RUNS))) \
	  --out $(or $(REPORT),data/report-hard-cases)

REAL_SCENES ?=
REAL_RUNS ?= $(wildcard data/runs/*/checkpoint.pt data/runs-temporal/*/checkpoint.pt data/runs-nppd/*/checkpoint.pt)
CHAOS_SEED ?= 0
CHAOS_FAULTS ?= 20
chaos: setup     ## configs/chaos.yaml (300 frames) into a local S3 server through CHAOS_FAULTS random faults, then training through 5 SIGKILLs; compared with clean runs (seeded: CHAOS_SEED)
	$(PY) scripts/chaos.py --seed $(CHAOS_SEED) --faults $(CHAOS_FAULTS)

real-scenes: setup ## the held-out real-scene suite (box and Gaussian filters; REAL_SCENES=DIR adds your folder of scene files): every trained run, its input and OIDN per scene (about 7 min on 2 cores)
	$(PY) -m scene_gen real-scenes --out $(DENOISE_DATA)/real-scenes
	$(PY) -m pipeline dataset --config configs/real-scenes.yaml
	$(PY) -m pipeline dataset --config configs/real-scenes.yaml --set render.filter=gaussian --set name=real-scenes-gaussian
	if [ -n "$(REAL_SCENES)" ]; then $(PY) -m pipeline dataset --config configs/real-scenes.yaml --set name=real-scenes-user \
	  --set 'scenes=[{file: "$(abspath $(REAL_SCENES))", camera: {jitter: 0.0, turn: 0.0, zoom: 0.0}}, {file: "$(abspath $(REAL_SCENES))"}]' \
	  --set render.filter=gaussian || exit 1; fi
	$(PY) -m training real-scenes --runs $(or $(RUNS),$(dir $(REAL_RUNS))) --store $(DENOISE_DATA)/real-scenes.zarr \
	  --store $(DENOISE_DATA)/real-scenes-gaussian.zarr $(if $(REAL_SCENES),--store $(DENOISE_DATA)/real-scenes-user.zarr) \
	  --out $(or $(REPORT),data/report-real-scenes)

preview: setup   ## render a preview of one scene: SEED, KIND
	$(PY) -m scene_gen preview --seed $(or $(SEED),0) --kind $(or $(KIND),indoor) --res 256 --spp 64 --out data/preview/$(or $(KIND),indoor)-$(or $(SEED),0).exr

contact-sheet: setup ## the README's contact sheet of 16 random scenes
	$(PY) -m scene_gen contact-sheet --count 16 --res 160 --spp 64 --out docs/contact_sheet.png

clean-data:      ## remove generated data (stores, renders, checkpoints)
	rm -rf data
