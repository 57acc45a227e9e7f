# Two-command quick start: `make demo` (main job on simulated hardware) and `make test`.
# Both create .venv inside the repository on first use and install the pinned requirements.

PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
export PYTHONPATH := $(CURDIR)$(if $(PYTHONPATH),:$(PYTHONPATH))

.PHONY: venv demo test bench bench-calibration bench-calibration-speed bench-interior bench-exterior-reach bench-reach-selection bench-reach-guess bench-interior-diagnosis bench-offset-diagnosis bench-realdata bench-realdata-halves bench-realdata-consistency bench-short-scan bench-conjugate-modes bench-embedding bench-sweep bench-guard bench-dask bench-fullsize bench-streaming clean

CLI    := $(VENV)/bin/robot-ct

venv: $(STAMP) $(CLI)

$(STAMP): requirements.txt requirements-test.txt
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements-test.txt
	touch $(STAMP)

# The venv finds this checkout from any folder (a .pth file; no copy, edits take effect at once), and
# .venv/bin/robot-ct runs the command line: on the PATH after `source .venv/bin/activate`.
$(CLI): $(STAMP) Makefile
	$(PY) -c "import site, sys; open(site.getsitepackages()[0] + '/robot_ct_ros_checkout.pth', 'w').write(sys.argv[1] + '\\n')" "$(CURDIR)"
	printf '#!/bin/sh\n# robot-ct from this checkout (written by make venv)\nexec "%s" -m robot_ct_ros.cli "$$@"\n' "$(CURDIR)/$(PY)" > $(CLI)
	chmod +x $(CLI)

demo: $(STAMP) $(CLI)
	$(PY) -m robot_ct_ros.cli demo --out out/demo

test: $(STAMP) $(CLI)
	$(PY) -m pytest

bench: $(STAMP)
	$(PY) bench/bench_projector.py --rtk-back --out docs/results
	$(PY) bench/bench_fdk.py --out docs/results

bench-calibration: $(STAMP)
	$(PY) bench/bench_calibration.py --repeats 3 --out docs/results

bench-calibration-speed: $(STAMP)
	$(PY) bench/bench_calibration_speed.py --json docs/results/speed.json

bench-interior: $(STAMP)
	$(PY) bench/bench_interior.py --oracle --out docs/results

bench-exterior-reach: $(STAMP)
	$(PY) bench/bench_exterior_reach.py --out docs/results

bench-reach-selection: $(STAMP)
	$(PY) bench/bench_reach_selection.py --out docs/results

bench-reach-guess: $(STAMP)
	$(PY) bench/bench_reach_guess.py --out docs/results
	$(PY) bench/bench_reach_guess.py --cases bags --out docs/results/reach_guess_bags

bench-interior-diagnosis: $(STAMP)
	$(PY) bench/bench_interior_diagnosis.py --out docs/results

bench-offset-diagnosis: $(STAMP)
	$(PY) bench/bench_offset_diagnosis.py --out docs/results

bench-realdata: $(STAMP)
	$(PY) bench/bench_realdata.py --out docs/results

bench-realdata-halves: $(STAMP)
	$(PY) bench/bench_realdata_halves.py --out docs/results

bench-realdata-consistency: $(STAMP)
	$(PY) bench/bench_realdata_consistency.py --out docs/results

bench-short-scan: $(STAMP)
	$(PY) bench/bench_short_scan.py --out docs/results

bench-conjugate-modes: $(STAMP)
	$(PY) bench/bench_conjugate_modes.py --out docs/results

bench-embedding: $(STAMP)
	$(PY) bench/bench_embedding.py --out docs/results

bench-sweep: $(STAMP)
	$(PY) bench/bench_truncation_sweep.py --out docs/results

bench-guard: $(STAMP)  # reads the other benches' json: run it after them
	$(PY) bench/bench_guard.py --results docs/results --out docs/results

bench-dask: $(STAMP)
	$(PY) bench/bench_dask.py --out docs/results

bench-fullsize: $(STAMP)
	$(PY) bench/bench_fullsize.py --rtk-binning 2 --out docs/results --volume-out out/bench_fullsize

bench-streaming: $(STAMP)
	$(PY) bench/bench_streaming.py --out docs/results

clean:
	rm -rf out build install log .pytest_cache
	find . -name __pycache__ -not -path './$(VENV)/*' -prune -exec rm -rf {} +
