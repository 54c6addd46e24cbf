# Two commands do all set-up on a fresh machine: `make run` and `make test`.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q -e '.[test,mqtt]'
	touch $(STAMP)

venv: $(STAMP)

# The daemon, and beside it the operator view (lathed-web prints its URL); Ctrl-C stops both.
run: $(STAMP)
	@$(BIN)/lathed-web --config etc/lathed-web.toml & web=$$!; \
	trap 'kill $$web 2>/dev/null' EXIT INT TERM; \
	$(BIN)/lathed --config etc/lathed.toml

test: $(STAMP)
	bash tests/ensure_postgres.sh
	bash tests/ensure_chromium.sh
	bash tests/ensure_mosquitto.sh
	$(BIN)/python -m pytest -n 2 --dist loadfile

# Benchmarks: each prints a Markdown table (the README's performance section).
bench-daemon: $(STAMP)
	$(BIN)/python bench/bench_daemon.py
bench-chatter: $(STAMP)
	$(BIN)/python bench/bench_chatter.py --with-reference
bench-suppression: $(STAMP)
	$(BIN)/python bench/bench_suppression.py
bench-loop: $(STAMP)
	$(BIN)/python bench/bench_loop.py
	$(BIN)/python bench/bench_loop.py --avoid
bench-thermal: $(STAMP)
	$(BIN)/python bench/bench_thermal.py
bench-store: $(STAMP)
	$(BIN)/python bench/bench_store.py
bench-stability: $(STAMP)
	$(BIN)/python bench/bench_stability.py
# issue 18: 10 minutes of hostile load (DURATION=60 for a quick look)
DURATION ?= 600
bench-hostile: $(STAMP)
	$(BIN)/python bench/bench_hostile.py --duration $(DURATION)
# issue 14: the operator view's cost, 5 Chromium pages (tests/ensure_chromium.sh installs chromium)
bench-web: $(STAMP)
	bash tests/ensure_chromium.sh
	$(BIN)/python bench/bench_web.py
# issue 15: MQTT end to end with a broker restart (tests/ensure_mosquitto.sh installs mosquitto)
bench-plant-mqtt: $(STAMP)
	bash tests/ensure_mosquitto.sh
	$(BIN)/python bench/bench_plant_mqtt.py
bench: bench-daemon bench-chatter bench-suppression bench-loop bench-thermal bench-store bench-stability \
	bench-hostile bench-web bench-plant-mqtt

.PHONY: venv run test bench bench-daemon bench-chatter bench-suppression bench-loop bench-thermal bench-store \
	bench-stability bench-hostile bench-web bench-plant-mqtt
