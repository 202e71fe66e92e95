# Gesture-recognition ablation table (paper Appendix B layout: model x modality x features -> Acc, F1,
# Prec., Rec.) from a folder of labelled sessions. Included from the Makefile (needs $(BIN), `install`).
#   make gestures-table                        simulated Raven-II peg transfer (15 trials), paper grid
#   make gestures-table DATA=path/to/dataset   any folder of labelled session folders
#   make gestures-table GESTURES_EPOCHS=5 GESTURES_GRID="emht:pos,ori,vel:exclude-clutch"   quick look
# The dataset and its .simulated stamp are the same as `make tables` uses, so both share one simulation.
# Runs already in $(GESTURES_DIR)/runs/ are reused (delete the folder to retrain).
#   make gestures-table EXECUTOR=slurm SLURM_ARGS="--slurm-partition gpu --slurm-time 02:00:00"
#                                              every (model, row) cell a SLURM array task (and the
#                                              sessions not aligned yet one align array)
TABLES_DIR ?= results
TABLES_SEED ?= 1
MIDAS_BIN ?= $(BIN)/midas
GESTURES_DATA ?= $(if $(DATA),$(DATA),$(TABLES_DIR)/simulated/raven-ii)
GESTURES_DIR ?= $(TABLES_DIR)/gestures/$(notdir $(GESTURES_DATA))
GESTURES_MODELS ?= transformer,mstcn
GESTURES_EPOCHS ?= 50
# the paper's models trained on the inputs as they are: no shift augmentation (MS-TCN++'s recipe has one)
GESTURES_AUGMENT_SHIFT ?= 0
GESTURES_SPLIT ?= gesture
# where torch trains: cpu or cuda (GESTURES_DEVICE, its old name, still works)
GESTURES_ACCELERATOR ?= $(or $(GESTURES_DEVICE),cpu)
GESTURES_GRID ?=
EXECUTOR ?= local
SLURM_ARGS ?=
$(if $(filter $(EXECUTOR),local slurm),,$(error EXECUTOR must be local or slurm, not '$(EXECUTOR)'))
_GESTURES_EXECUTOR = --executor $(EXECUTOR) $(if $(filter slurm,$(EXECUTOR)),$(SLURM_ARGS),)

.PHONY: gestures-table

gestures-table: install
	@if [ -z "$(DATA)" ] && [ ! -f $(GESTURES_DATA)/.simulated ]; then \
		$(MIDAS_BIN) simulate dataset --platform raven-ii --trials 15 --seed $(TABLES_SEED) \
			--out $(GESTURES_DATA) > /dev/null && touch $(GESTURES_DATA)/.simulated || exit 1; \
	fi
	@todo=""; for s in $(GESTURES_DATA)/*/; do \
		[ -f "$$s/derived/aligned.json" ] || todo="$$todo $$s"; \
	done; \
	if [ -n "$$todo" ]; then $(MIDAS_BIN) align $$todo $(_GESTURES_EXECUTOR) > /dev/null || exit 1; fi
	$(MIDAS_BIN) train ablation $(GESTURES_DATA) --models $(GESTURES_MODELS) --epochs $(GESTURES_EPOCHS) \
		--augment-shift $(GESTURES_AUGMENT_SHIFT) --split $(GESTURES_SPLIT) --accelerator $(GESTURES_ACCELERATOR) $(if $(GESTURES_GRID),--grid "$(GESTURES_GRID)",) \
		$(_GESTURES_EXECUTOR) --out $(GESTURES_DIR) > /dev/null
	@echo "gesture table: $(GESTURES_DIR)/table.md (.tex, .csv)"
