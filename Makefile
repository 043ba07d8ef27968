# Set-up is part of every target: a missing .venv is created, torch is installed first from
# the pinned CPU wheel (an unpinned torch would pull a multi-GB CUDA build), then the package.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: demo test test-slow docs bench bench-matrix bench-million bench-scale reproduce road ksvd real real-imm recorded recorded-faults recorded-wide recorded-wide-family recorded-vehicles recorded-sparse recorded-held-out recorded-noise bias-detectability per-track-choice blend-weights network-psi learn imm-svsf-kf lint clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet torch==2.13.0
	$(PY) -m pip install --quiet -e ".[dev]"
	# The recorded ADS-B flights (about 30 MB) without traffic's own dependencies.
	$(PY) -m pip install --quiet --no-deps traffic==2.13
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m experiments.demo

# Two pytest workers share the two cores (tests/conftest.py builds the compiled loops once first).
test: $(STAMP)
	$(PY) -m pytest -m "not slow" -q -n 2

test-slow: $(STAMP)
	$(PY) -m pytest -m slow -q

# The docs site (mkdocs.yml, docs/; the reports of experiments/results and benchmarks join it):
# any warning fails the build.
docs: $(STAMP)
	NO_MKDOCS_2_WARNING=1 $(VENV)/bin/mkdocs build --strict --quiet --site-dir site

bench: $(STAMP)
	$(PY) -m benchmarks.forward
	$(PY) -m benchmarks.particles
	$(PY) -m benchmarks.threads
	$(PY) -m benchmarks.step_overhead
	$(PY) -m benchmarks.one_track
	$(PY) -m benchmarks.training
	$(PY) -m benchmarks.ddp_predict
	$(PY) -m benchmarks.compiled_steps
	$(PY) -m benchmarks.covariance_forms
	$(PY) -m benchmarks.imm_track
	$(PY) -m benchmarks.defaults_phases

# The full matrix (every estimator × B × dtype × pass beside four peers): most of an hour.
bench-matrix: $(STAMP)
	$(PY) -m benchmarks.matrix

bench-million: $(STAMP)
	$(PY) -m benchmarks.million_tracks

# One Parquet dataset (100 M rows, 100 files) through torchsvs track, Spark local[2] and Dask
# beside pyarrow's floor, with the cost model: benchmarks/scale.md (about half an hour).
bench-scale: $(STAMP)
	$(PY) -m benchmarks.scale --rows 100000000 --small 10000000 --files 100
	$(PY) -m benchmarks.floor_pairs --rows 10000000 --files 10 --pairs 12

real: $(STAMP)
	$(PY) -m experiments.real_flights

# Every estimator of `torchsvs track`, as a user runs it (no options, --fit, --meas-std σ, both),
# on recorded tracks of several kinds (own report times, 10 s and 1 s scans, taxiing, irregular,
# simulated turns; σ 10-100 m): experiments/results/recorded_tracks.md.
recorded: $(STAMP)
	$(PY) -m experiments.recorded_tracks

# The same with realistic faults (outliers, lost rows, time jitter, a bias that comes and goes):
# KS, RSTKF, SVSS and auto at σ 50, experiments/results/recorded_faults.md.
recorded-faults: $(STAMP)
	$(PY) -m experiments.recorded_tracks --faults --kinds own,scan10,taxi,turning --sigmas 50 \
		--estimators ks,svsf,svss,svstps,rstkf,auto --modes default,--fit --jobs 2

# The same kinds beyond the benchmark's noise levels (σ 3 m and 250 m), defaults only:
# experiments/results/recorded_wide.md (where the defaults meet their limits).
recorded-wide: $(STAMP)
	$(PY) -m experiments.recorded_tracks --kinds own,scan1,taxi,turning,scan10 --sigmas 3,250 \
		--modes default --name recorded_wide

# The SVSF family against the Kalman smoother at σ 3 m and 250 m, every mode (the layer check
# held out: its rule was set on recorded_tracks.md): experiments/results/recorded_wide_family.md.
recorded-wide-family: $(STAMP)
	$(PY) -m experiments.recorded_tracks --kinds own,scan10,scan1,taxi,turning --sigmas 3,250 \
		--estimators ks,svss,svstps --jobs 2 --name recorded_wide_family

# Simulated other vehicles (people walking, cars, ships by AIS, drones at 10 Hz): every
# estimator and mode, then with faults (~35 min)
recorded-vehicles: $(STAMP)
	$(PY) -m experiments.recorded_tracks --kinds walker,car,ship,drone --jobs 2 \
		--name recorded_vehicles
	$(PY) -m experiments.recorded_tracks --faults --kinds walker,car,ship,drone --jobs 2 \
		--estimators ks,svsf,svss,svstps,rstkf,auto --modes default,--fit \
		--name recorded_vehicles_faults

# Vehicles reporting far apart (vans every 60 s, ships by satellite AIS every 5-60 min, city
# buses every 30 s), where the motion between reports reads as noise:
# experiments/results/recorded_sparse.md.
recorded-sparse: $(STAMP)
	$(PY) -m experiments.recorded_tracks --kinds van,satship,bus --jobs 2 --name recorded_sparse

# Every kind, aircraft and simulated vehicles, at noise levels the benchmarks above do not use
# and draws they never saw: σ 25 m (seed 2, defaults and --fit), experiments/results/
# recorded_held_out.md, and σ 5 and 150 m (seed 3, defaults), recorded_held_out_wide.md (~20 min).
HELD_OUT_KINDS := own,scan10,scan1,taxi,irregular,turning,walker,car,ship,drone
recorded-held-out: $(STAMP)
	$(PY) -m experiments.recorded_tracks --kinds $(HELD_OUT_KINDS) --sigmas 25 --seed 2 \
		--modes default,--fit --jobs 2 --name recorded_held_out
	$(PY) -m experiments.recorded_tracks --kinds $(HELD_OUT_KINDS) --sigmas 5,150 --seed 3 \
		--modes default --jobs 2 --name recorded_held_out_wide

# Every kind measured with noise other than the white Gaussian the estimators assume: each
# track its own σ (mixed; defaults, and each row's σ given by --noise-col), Student's t
# (heavy), correlated in time (correlated), defaults: experiments/results/recorded_mixed.md,
# recorded_heavy.md, recorded_correlated.md (~8 min).
recorded-noise: $(STAMP)
	$(PY) -m experiments.recorded_tracks --noise mixed --kinds $(HELD_OUT_KINDS) \
		--estimators ks,svss,svstps,imm,auto --modes "default,--noise-col sigma" --jobs 2
	for noise in heavy correlated; do \
		$(PY) -m experiments.recorded_tracks --noise $$noise --kinds $(HELD_OUT_KINDS) \
			--estimators ks,svss,svstps,imm,auto --modes default --jobs 2 || exit 1; \
	done

# Whether the faults benchmark's sensor bias can be found in the measurements (NumPy, ~1 min):
bias-detectability: $(STAMP)
	$(PY) -m experiments.bias_detectability

# The Kalman smoother or the IMM smoother chosen per track: the room (truth) and a truth-free
# rule's share of it, on the recorded and simulated sets (~1 min)
per-track-choice: $(STAMP)
	$(PY) -m experiments.per_track_choice

# auto's blend of the Kalman and IMM smoothers: a weight per file or per track (~1 min):
# experiments/results/blend_weights.md
blend-weights: $(STAMP)
	$(PY) -m experiments.blend_weights

# ψ per step from a network trained by SURE (no truth) on recorded tracks, scored on held-out
# halves of every kind: experiments/results/network_psi.md.
network-psi: $(STAMP)
	$(PY) -m experiments.network_psi

# Only the IMM(CV, CT) rows and section of real_flights.md, merged into the recorded report.
real-imm: $(STAMP)
	$(PY) -m experiments.real_flights --only-imm

reproduce: $(STAMP)
	$(PY) -m experiments.svss_paper
	$(PY) -m experiments.spvsf_paper
	$(PY) -m experiments.road_tracking
	$(PY) -m experiments.ksvd_paper

# Zhang & Zhou 2022 alone: the separate-modeling road tracker beside its baselines.
road: $(STAMP)
	$(PY) -m experiments.road_tracking

# Bermúdez Ordoñez et al. 2020 alone: Examples 1 and 4 per covariance form, the adaptive R.
ksvd: $(STAMP)
	$(PY) -m experiments.ksvd_paper

learn: $(STAMP)
	$(PY) -m experiments.learn_psi
	$(PY) -m experiments.adaptive_psi

# Beyond the papers: an IMM of the SVSF and a KF on Chen et al. 2020's complex scenario.
imm-svsf-kf: $(STAMP)
	$(PY) -m experiments.imm_svsf_kf

lint: $(STAMP)
	$(VENV)/bin/ruff check torchsvs tests experiments benchmarks
	$(VENV)/bin/ruff format --check torchsvs tests experiments benchmarks
	$(VENV)/bin/mypy

clean:
	rm -rf $(VENV) .pytest_cache
