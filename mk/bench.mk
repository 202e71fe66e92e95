# `make bench`: every benchmark in benchmarks/ (reproducible timings, never tests), then BENCHMARKS.md at the
# repository root from benchmarks/results/*.json. Included from the Makefile (needs $(BIN) and `install`).
#   make bench                    full run, with a 5-minute soak (about 25-30 minutes on 2 idle cores)
#   make bench BENCH_QUICK=1      smoke run of every script (about 7 minutes; the soak records 2 minutes)
#   make bench SOAK_MIN=10        the soak inside bench at another length (results/soak-short.json)
#   make soak                     the 30-minute soak alone (results/soak.json, .png), then BENCHMARKS.md
#   make soak SOAK_MIN=60         a longer one
# `make bench` never replaces results/soak.json: a long soak run once with `make soak` stays in the report.
BENCH_QUICK ?=
_BENCH_FLAG := $(if $(BENCH_QUICK),--quick,)
_BENCH_PEDAL_S := $(if $(BENCH_QUICK),3,10)

.PHONY: bench soak

bench: install
	$(BIN)/python benchmarks/bench_startup.py $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/bench_record.py $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/bench_soak.py --minutes $(or $(SOAK_MIN),5) --name soak-short $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/bench_align.py $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/bench_batch.py $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/bench_export.py $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/bench_pedal_gt.py --duration $(_BENCH_PEDAL_S) > /dev/null
	$(BIN)/python benchmarks/bench_train.py $(_BENCH_FLAG) > /dev/null
	$(if $(BENCH_QUICK),,$(BIN)/python benchmarks/bench_train.py --louo > /dev/null)
	$(BIN)/python benchmarks/bench_mstcn_reference.py --threads 1 $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/bench_fold_batch.py $(_BENCH_FLAG) > /dev/null
	$(BIN)/python benchmarks/bench_timestamp_error.py $(_BENCH_FLAG) > /dev/null
	if [ -x /usr/sbin/slurmctld ] || command -v slurmctld > /dev/null; then \
		$(BIN)/python benchmarks/bench_executor.py $(_BENCH_FLAG) > /dev/null; \
	else echo "bench_executor.py skipped: no SLURM (apt-get install slurm-wlm munge)"; fi
	$(BIN)/python benchmarks/report.py

soak: install
	$(BIN)/python benchmarks/bench_soak.py --minutes $(or $(SOAK_MIN),30) --name soak > /dev/null
	$(BIN)/python benchmarks/report.py
