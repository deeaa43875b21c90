# fingerps: set-up, build, demo, tests, benchmarks. Every target sets up what it needs.
#   make demo   - the whole graph on the simulated rig, with a summary
#   make test   - the whole test suite
#   make bench  - every benchmark (the speed ones natively and with AVX-512 off); figures into bench/results.json
#   make soak   - 30 min of the bringup graph at 5 bursts/s (not in bench); soak.* into bench/results.json
#   make firmware - the LED board's firmware (.elf/.hex) and its simavr harness into build/firmware
SHELL := /bin/bash
.SHELLFLAGS := -e -o pipefail -c
PYTHON ?= python3
STAMPS := .stamps
ROS := source tools/ros_env.sh &&
SRC_FILES := $(shell find src -type f \( -name '*.py' -o -name '*.xml' -o -name '*.txt' \
               -o -name '*.msg' -o -name '*.srv' -o -name '*.action' -o -name '*.cfg' \
               -o -name '*.yaml' -o -name '*.json' -o -name '*.rviz' \) -not -path '*/__pycache__/*')

.PHONY: setup build firmware demo test bench soak lint clean
.DEFAULT_GOAL := demo

setup: $(STAMPS)/venv
build: $(STAMPS)/build

$(STAMPS)/venv: requirements.txt constraints.txt tools/mend_ros_wheel_cmake.py
	@mkdir -p $(STAMPS)
	@test -x .venv/bin/python || $(PYTHON) -m venv .venv
	.venv/bin/python -m pip install --quiet --disable-pip-version-check \
	    -r requirements.txt -c constraints.txt
	.venv/bin/python tools/mend_ros_wheel_cmake.py
	@touch $@

# --symlink-install: Python sources are used in place, so editing a node needs no rebuild.
# Then the numba kernels are compiled into their on-disk cache, so that no node compiles
# during a demo, a test or a measurement.
# The firmware is order-only: its own make rebuilds what changed, and a firmware change
# needs no colcon build.
$(STAMPS)/build: $(STAMPS)/venv $(SRC_FILES) | firmware
	$(ROS) colcon --log-base log build --symlink-install \
	    --event-handlers console_cohesion- status- summary+ \
	    --cmake-args -DBUILD_TESTING=OFF
	$(ROS) python -m fingerps_recon.photometric.kernel_warm_up
	@touch $@

# The LED board's firmware (ATmega328P) and the simavr harness the tests run it in; the
# Debian packages they need are installed first when missing (as root; otherwise the
# apt-get line to run is printed).
firmware:
	tools/firmware_packages.sh
	$(MAKE) -C src/fingerps_driver/firmware OUT=$(CURDIR)/build/firmware

demo: build
	$(ROS) ros2_run() { "install/$$1/lib/$$1/$$2" "$${@:3}"; }; \
	    ros2_run fingerps_driver demo --out out/demo

test: build
	$(ROS) python -m pytest -q tests

bench: build
	$(ROS) python bench/run_all.py --out bench/results.json

soak: build
	$(ROS) python bench/bench_soak.py --minutes 30 --out bench/results.json

lint: $(STAMPS)/venv
	.venv/bin/ruff check src tests bench tools

clean:
	rm -rf build install log $(STAMPS)
