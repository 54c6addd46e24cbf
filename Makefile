# Two commands do all set-up on a fresh machine: `make run` and `make test`.
PY ?= python3.11
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

$(STAMP): pyproject.toml
	$(PY) -m venv $(VENV)
# uv installs what pip did, its downloads and bytecode compiled in parallel: the set-up took
# 44 s of a fresh clone's make test with pip, 23 s with uv and an empty uv cache (bytecode is
# compiled here: left to the suite's first imports, it cost the tests as much again)
	$(BIN)/pip install -q uv
	VIRTUAL_ENV=$(abspath $(VENV)) $(BIN)/uv pip install -q --compile-bytecode -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

# The daemon, and beside it the operator view and the OPC UA server on loopback (lathed-web
# and lathed-opcua print their URLs); Ctrl-C stops all three. On a terminal, job control
# (set -m) gives the daemon the terminal: Ctrl-C reaches it alone, it stops its drivers and
# exits 0, the other two are stopped after it, and make too exits 0 (without it, make gets
# the SIGINT as well and reports "Interrupt" whatever the daemon did).
run: $(STAMP)
	@[ -t 0 ] && set -m; \
	$(BIN)/lathed-web --config etc/lathed-web.toml & web=$$!; \
	$(BIN)/lathed-opcua --config etc/lathed-opcua.toml & opcua=$$!; \
	trap 'kill $$web $$opcua 2>/dev/null; wait $$web $$opcua 2>/dev/null' EXIT INT TERM; \
	$(BIN)/lathed --config etc/lathed.toml

test: $(STAMP)
	bash tests/ensure_postgres.sh
	bash tests/ensure_chromium.sh
	bash tests/ensure_mosquitto.sh
	bash tests/ensure_node_opcua.sh
	bash tests/ensure_jack.sh
# Bytecode is written (__pycache__/, git ignores it) even where the environment says not to:
# without it each of the suite's processes (workers, daemons, simulators, lathectl) compiled
# lathed from source, and each worker re-did pytest's assertion rewriting (15 against 7.5 CPU-s).
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -n 6 --dist loadfile --no-loadscope-reorder

# Benchmarks: each prints a Markdown table (docs/benchmarks.md).
bench-daemon: $(STAMP)
	$(BIN)/python bench/bench_daemon.py
bench-chatter: $(STAMP)
	$(BIN)/python bench/bench_chatter.py --with-reference
bench-suppression: $(STAMP)
	$(BIN)/python bench/bench_suppression.py
bench-loop: $(STAMP)
	$(BIN)/python bench/bench_loop.py
	$(BIN)/python bench/bench_loop.py --avoid
	$(BIN)/python bench/bench_loop.py --remember
	$(BIN)/python bench/bench_loop.py --opcua
bench-thermal: $(STAMP)
	$(BIN)/python bench/bench_thermal.py
bench-store: $(STAMP)
	$(BIN)/python bench/bench_store.py
bench-stability: $(STAMP)
	$(BIN)/python bench/bench_stability.py
	$(BIN)/python bench/stability_learn.py
# issue 18: 10 minutes of hostile load (DURATION=60 for a quick look)
DURATION ?= 600
bench-hostile: $(STAMP)
	$(BIN)/python bench/bench_hostile.py --duration $(DURATION)
# issue 14: the operator view's cost, 5 Chromium pages (tests/ensure_chromium.sh installs chromium)
bench-web: $(STAMP)
	bash tests/ensure_chromium.sh
	$(BIN)/python bench/bench_web.py
# issue 15: OPC UA subscription latency with 10 clients, CPU/RSS of lathed and lathed-opcua
bench-plant-opcua: $(STAMP)
	$(BIN)/python bench/bench_plant_opcua.py
# issue 15: MQTT end to end with a broker restart (tests/ensure_mosquitto.sh installs mosquitto)
bench-plant-mqtt: $(STAMP)
	bash tests/ensure_mosquitto.sh
	$(BIN)/python bench/bench_plant_mqtt.py
bench: bench-daemon bench-chatter bench-suppression bench-loop bench-thermal bench-store bench-stability \
	bench-hostile bench-web bench-plant bench-channels
# issue 37: audio accelerometers, 1/2/4/8 channels at 51.2 kS/s each with a chatter analyzer
# (a JACK server with its dummy backend stands in for the interface: tests/ensure_jack.sh)
bench-channels: $(STAMP)
	bash tests/ensure_jack.sh
	$(BIN)/python bench/bench_channels.py
# its per-block path in-process, stage by stage; AGAINST=REV runs REV's code beside this one
# (alternating, the same signal) and checks both published the same chatter samples
bench-channel-path: $(STAMP)
	$(BIN)/python bench/bench_channel_path.py $(if $(AGAINST),--against $(AGAINST))
# CPU seconds from exec to ready of each program the suite starts many times; AGAINST=REV
# alternates REV's code with this one
bench-startup: $(STAMP)
	$(BIN)/python bench/bench_startup.py $(if $(AGAINST),--against $(AGAINST))
# issue 15: both plant protocols
bench-plant: bench-plant-mqtt bench-plant-opcua

# --- Installed as a service (docs/installation.md) ---------------------------
# A wheel of this checkout (not editable, no test tools) in a venv of its own at
# $(PREFIX)/lib/lathed, with links in $(PREFIX)/bin, the systemd units, sysusers.d and
# tmpfiles.d files; the config goes to /etc/lathed only where none is yet. /usr/lib
# rather than /opt: the units, sysusers.d and tmpfiles.d files belong under /usr/lib
# anyway (systemd has no /opt for them), so one PREFIX names all that uninstall takes.
# DESTDIR stages the tree for a package: the venv is built there, then its paths are
# rewritten to the final ones (scripts' #! lines, bytecode's file names).
PREFIX ?= /usr
DESTDIR ?=
EXTRAS ?=                       # e.g. EXTRAS=postgres,plots,opcua,mqtt,recordings,audio (opcua: lathed-opcua, opcua_cnc)
LIBDIR = $(PREFIX)/lib/lathed
BINDIR = $(PREFIX)/bin
DOCDIR = $(PREFIX)/share/doc/lathed
UNITDIR ?= /lib/systemd/system
SYSUSERSDIR ?= $(PREFIX)/lib/sysusers.d
TMPFILESDIR ?= $(PREFIX)/lib/tmpfiles.d
CONFDIR ?= /etc/lathed
PROGRAMS := lathed lathectl lathed-web lathed-opcua lathed-sim
UNITS := lathed.service lathed-web.service lathed-opcua.service
STAGE = $(DESTDIR)$(LIBDIR)
# etc/ as git tracks it (a file left there untracked is not shipped); all of it outside a checkout
ETC_FILES := $(shell if git -C . rev-parse --is-inside-work-tree >/dev/null 2>&1; then git -C . ls-files etc; \
	else find etc -type f; fi)

install: install-venv install-config
	install -d $(DESTDIR)$(BINDIR) $(DESTDIR)$(UNITDIR) $(DESTDIR)$(SYSUSERSDIR) $(DESTDIR)$(TMPFILESDIR) \
		$(DESTDIR)$(DOCDIR)/examples
	for p in $(PROGRAMS); do ln -sfn $(LIBDIR)/bin/$$p $(DESTDIR)$(BINDIR)/$$p; done
	for u in $(UNITS); do sed -e 's|/usr/lib/lathed/|$(LIBDIR)/|g' -e 's|/usr/share/doc/lathed/|$(DOCDIR)/|g' \
		systemd/$$u > $(DESTDIR)$(UNITDIR)/$$u && chmod 0644 $(DESTDIR)$(UNITDIR)/$$u; done
	install -m 0644 systemd/lathed.sysusers $(DESTDIR)$(SYSUSERSDIR)/lathed.conf
	install -m 0644 systemd/lathed.tmpfiles $(DESTDIR)$(TMPFILESDIR)/lathed.conf
	install -m 0644 README.md $(DESTDIR)$(DOCDIR)/
	install -d $(DESTDIR)$(DOCDIR)/docs && install -m 0644 docs/*.md $(DESTDIR)$(DOCDIR)/docs/
# this version's defaults, to compare with an edited /etc/lathed after an upgrade
	for f in $(ETC_FILES); do install -D -m 0644 $$f $(DESTDIR)$(DOCDIR)/examples/$${f#etc/}; done
	@if [ -z "$(DESTDIR)" ]; then \
		systemd-sysusers $(SYSUSERSDIR)/lathed.conf && systemd-tmpfiles --create $(TMPFILESDIR)/lathed.conf; \
		if [ -d /run/systemd/system ]; then systemctl daemon-reload; fi; \
		echo "installed; edit $(CONFDIR)/lathed.toml, then: systemctl enable --now lathed lathed-web"; fi

install-venv:
	@case "$$($(PY) -c 'import os, sys; print(os.path.realpath(sys.base_prefix))')" in /home/*|/root/*) \
		echo "warning: $(PY) lives under /home or /root, which the units' ProtectHome= hides from the" \
		     "service; give PY=/usr/bin/python3.11";; esac
	$(PY) -m venv --clear $(STAGE)
# The wheel is built from a copy: a build in the checkout leaves files there (root's, under sudo).
	tmp=$$(mktemp -d) && trap 'rm -rf "$$tmp"' EXIT && mkdir "$$tmp/src" && \
	tar -c --exclude=./.venv --exclude=./.git --exclude=./build --exclude=./var --exclude=./out . | \
		tar -x -C "$$tmp/src" && \
	PIP_ROOT_USER_ACTION=ignore $(STAGE)/bin/pip wheel -q --no-deps -w "$$tmp/dist" "$$tmp/src" && \
	PIP_ROOT_USER_ACTION=ignore $(STAGE)/bin/pip install -q --no-compile -c constraints.txt \
		"$$(echo "$$tmp"/dist/lathed-*.whl)$(if $(strip $(EXTRAS)),[$(strip $(EXTRAS))])"
	@if [ -n "$(DESTDIR)" ]; then grep -rlIF -- '$(STAGE)' $(STAGE) | xargs -r sed -i 's|$(STAGE)|$(LIBDIR)|g'; fi
# all bytecode is compiled here, with the final paths (venv's pip wrote some, naming $(STAGE)),
# but the libraries' own test suites' (a third of scipy's and numpy's files, never imported by a
# service; a third of the compile time)
	find $(STAGE)/lib -name __pycache__ -prune -exec rm -rf {} +
	$(STAGE)/bin/python -m compileall -q -f -j 0 -x '/site-packages/[^/]+/(.+/)?tests/' \
		$(if $(DESTDIR),-s '$(DESTDIR)' -p /) $(STAGE)/lib
# how a missing extra is added to this venv (lathed/extras.py says it)
	echo "prefix=$(PREFIX)" > $(STAGE)/lathed-install

# Never overwrites a config that is there: an edited one stays as it is.
install-config:
	install -d -m 0750 $(DESTDIR)$(CONFDIR)
	for f in lathed.toml lathed-web.toml lathed-opcua.toml; do [ -e $(DESTDIR)$(CONFDIR)/$$f ] || \
		install -m 0640 etc/$$f $(DESTDIR)$(CONFDIR)/$$f; done
	[ -e $(DESTDIR)$(CONFDIR)/robot_arm.dbc ] || install -m 0644 etc/robot_arm.dbc $(DESTDIR)$(CONFDIR)/
	[ -e $(DESTDIR)$(CONFDIR)/plugins.d ] || for f in $(filter etc/plugins.d/%,$(ETC_FILES)); do \
		install -D -m 0644 $$f $(DESTDIR)$(CONFDIR)/$${f#etc/}; done

# What install put, but the config, the records (/var/lib/lathed) and the users.
uninstall:
	@if [ -z "$(DESTDIR)" ] && [ -d /run/systemd/system ]; then systemctl disable --now $(UNITS) || true; fi
	for p in $(PROGRAMS); do l=$(DESTDIR)$(BINDIR)/$$p; \
		if [ "$$(readlink $$l)" = "$(LIBDIR)/bin/$$p" ]; then rm -f $$l; fi; done
	for u in $(UNITS); do rm -f $(DESTDIR)$(UNITDIR)/$$u; done
	rm -f $(DESTDIR)$(SYSUSERSDIR)/lathed.conf $(DESTDIR)$(TMPFILESDIR)/lathed.conf
	rm -rf $(DESTDIR)$(DOCDIR)
	if [ -f $(STAGE)/pyvenv.cfg ]; then rm -rf $(STAGE); fi
	@if [ -z "$(DESTDIR)" ] && [ -d /run/systemd/system ]; then systemctl daemon-reload; fi
	@echo "kept: $(CONFDIR) (config), /var/lib/lathed (records), the users lathed, lathed-web, lathed-opcua"

.PHONY: install install-venv install-config uninstall
.PHONY: venv run test bench bench-daemon bench-chatter bench-suppression bench-loop bench-thermal bench-store \
	bench-stability bench-hostile bench-web bench-plant bench-plant-mqtt bench-plant-opcua bench-channels bench-startup
