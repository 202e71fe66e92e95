# `make tables`: the paper's validation tables end to end (simulate -> calibrate -> align -> eval) into
# results/. Included from the Makefile (needs $(BIN) and the `install` target from there).
#   make tables -j2                        simulated Raven-II (15 trials) + da Vinci Xi (17 trials)
#   make tables DATA=path/to/dataset -j8   any folder of session folders (no simulation; failed or
#                                          unfinished sessions are skipped)
#   make tables TABLES_MAX_SECONDS=60      short simulated trials (demos, CI)
# It ends with the gesture-recognition table (mk/gestures.mk: training on CPU takes a while; see
# GESTURES_EPOCHS / GESTURES_GRID / GESTURES_ACCELERATOR=cuda there).
# Per-session steps (align) are separate targets, so `make -j N` runs N sessions at once.
#   make tables EXECUTOR=slurm SLURM_ARGS="--slurm-time 00:20:00"
#                                          simulation and align as SLURM job arrays (one task per trial /
#                                          session; README "Running on a cluster"), run folders under
#                                          $(TABLES_DIR)/jobs/; calibration and eval run here
TABLES_DIR ?= results
TABLES_SEED ?= 1
TABLES_RAVEN_TRIALS ?= 15
TABLES_DAVINCI_TRIALS ?= 17
TABLES_MAX_SECONDS ?=
MIDAS_BIN ?= $(BIN)/midas
EXECUTOR ?= local
SLURM_ARGS ?=
$(if $(filter $(EXECUTOR),local slurm),,$(error EXECUTOR must be local or slurm, not '$(EXECUTOR)'))
_EXECUTOR_ARGS = --executor $(EXECUTOR) $(if $(filter slurm,$(EXECUTOR)),$(SLURM_ARGS),)
_TABLES_SIM := $(TABLES_DIR)/simulated
_TABLES_LIMIT := $(if $(TABLES_MAX_SECONDS),--max-seconds $(TABLES_MAX_SECONDS),)

ifdef DATA
_TABLES_DATASETS := $(DATA)
else
_TABLES_DATASETS := $(_TABLES_SIM)/raven-ii $(_TABLES_SIM)/davinci-xi
endif

.PHONY: tables tables-dataset

tables: install $(if $(DATA),,$(_TABLES_SIM)/raven-ii/.simulated $(_TABLES_SIM)/davinci-xi/.simulated)
	@for d in $(_TABLES_DATASETS); do \
		$(MAKE) --no-print-directory tables-dataset TABLES_DATA="$$d" TABLES_NAME="$$(basename $$d)" || exit 1; \
	done
	@echo "tables written under $(TABLES_DIR)/ (see each folder's *.md)"
	$(MAKE) --no-print-directory gestures-table

$(_TABLES_SIM)/%/.simulated:
	$(MIDAS_BIN) simulate dataset --platform $* --seed $(TABLES_SEED) --out $(@D) $(_TABLES_LIMIT) \
		--trials $(if $(filter raven-ii,$*),$(TABLES_RAVEN_TRIALS),$(TABLES_DAVINCI_TRIALS)) \
		$(_EXECUTOR_ARGS) $(if $(filter slurm,$(EXECUTOR)),--run-dir $(TABLES_DIR)/jobs/simulate-$*,) > /dev/null
	touch $@

# ---- one dataset (invoked recursively once its session folders exist) -------------------------------
# Its sessions are the finished session folders directly under TABLES_DATA: a recording that failed to
# start, or one still marked `recording` (running, or crashed: `midas session repair` it), is left out
# with a warning; `midas session list` reports folders it cannot read on stderr.
ifdef TABLES_DATA
_LIST := $(MIDAS_BIN) session list $(TABLES_DATA) --max-depth 1 --paths --status
_SESSIONS := $(shell $(_LIST) complete,interrupted,recovered)
_SKIPPED := $(shell $(_LIST) recording,failed 2> /dev/null)
$(if $(_SKIPPED),$(warning skipping unfinished or failed session(s): $(_SKIPPED)))
$(if $(_SESSIONS),,$(error no finished session folders under $(TABLES_DATA)))
endif
_ALIGNED := $(_SESSIONS:%=%/derived/aligned.json)
_RESULTS := $(TABLES_DIR)/$(TABLES_NAME)
_HAS_ROBOT = $(MIDAS_BIN) session info --json $(firstword $(_SESSIONS)) | grep -q '"mtm"'

tables-dataset: $(_RESULTS)/pedals.md $(_RESULTS)/.correlation

# calibrations use every session at once (leave-one-trial-out), then each session is aligned alone
$(TABLES_DATA)/.calibrated: $(_SESSIONS:%=%/manifest.json)
	if $(_HAS_ROBOT); then \
		for source in emht handkp; do for target in mtm psm; do \
			$(MIDAS_BIN) calibrate $$source $(_SESSIONS) --target $$target --out $(_RESULTS)/calib/$${source}_to_$${target}.json > /dev/null || exit 1; \
		done; done; \
	fi
	touch $@

ifeq ($(EXECUTOR),slurm)
# one job array for every session of the dataset; its run folder skips the sessions done
_ALIGN_DONE := $(_RESULTS)/.aligned
$(_ALIGN_DONE): $(_SESSIONS:%=%/manifest.json) $(TABLES_DATA)/.calibrated
	mkdir -p $(_RESULTS)
	$(MIDAS_BIN) align $(_SESSIONS) $(_EXECUTOR_ARGS) --run-dir $(TABLES_DIR)/jobs/align-$(TABLES_NAME) > /dev/null
	touch $@
else
_ALIGN_DONE := $(_ALIGNED)
endif

%/derived/aligned.json: %/manifest.json $(TABLES_DATA)/.calibrated
	$(MIDAS_BIN) align $* > /dev/null

$(_RESULTS)/.correlation: $(_ALIGN_DONE)
	mkdir -p $(_RESULTS)
	if $(_HAS_ROBOT); then $(MIDAS_BIN) eval correlation $(_SESSIONS) --out $(_RESULTS) > $(_RESULTS)/correlation.txt; fi
	touch $@

$(_RESULTS)/pedals.md: $(_ALIGN_DONE)
	mkdir -p $(_RESULTS)
	$(MIDAS_BIN) eval pedals $(_SESSIONS) --out $(_RESULTS) > $(_RESULTS)/pedals.txt
	$(MIDAS_BIN) calibrate fps-optimize $(_SESSIONS) --out $(_RESULTS)/fps_optimized.json > $(_RESULTS)/fps_optimized.txt
