# `make bench`: every benchmark in benchmarks/ (reproducible timings, never tests), then BENCHMARKS.md at the
# repository root from benchmarks/results/*.json. Included from the Makefile (needs $(BIN) and `install`).
#   make bench                    full run (about 10-15 minutes on 2 idle cores)
#   make bench BENCH_QUICK=1      smoke run of every script (about 3 minutes)
BENCH_QUICK ?=
_BENCH_FLAG := $(if $(BENCH_QUICK),--quick,)
_BENCH_PEDAL_S := $(if $(BENCH_QUICK),3,10)

.PHONY: bench

bench: install
	$(BIN)/python benchmarks/bench_record.py $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/bench_align.py $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/bench_pedal_gt.py --duration $(_BENCH_PEDAL_S) > /dev/null
	$(BIN)/python benchmarks/bench_train.py $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/report.py
