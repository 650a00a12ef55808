# cochlea: the two commands a new machine needs are `make demo` and `make test`.
# Both create the virtual environment (.venv) and install the package on first use.

PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test test-fast lint install clean realtime-check lib codegen bench robustness robustness-maps \
        embedded embedded-size embedded-sim bench-user tf2-msgs

# The stamp is rebuilt when the package's metadata changes.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

install: $(STAMP) lib

# The main job: the thesis's task-space study of the serial system (controller g) on the
# simulated robot, in real time under the supervisor; the log, summary.json and figures land in
# a new runs/serial_task_<date-time>/ folder whose path it prints.
demo: $(STAMP) lib
	$(BIN)/cochlea-run --robot serial --space task

# tf2_msgs, the type of /tf (issue 29): the package index has no wheel of it, so it is built
# from its one-line definition with the ROS 2 generators the test extra installs, cc and c++,
# and installed as the wheel cochlea-tf2-msgs (about 3 s the first time; then nothing: the
# installed version names its inputs). A build that fails is one line and stops nothing: the
# /tf tests of tests/test_ros2.py then fail and say so. See docs/logs.md.
tf2-msgs: $(STAMP)
	-$(BIN)/python -m cochlea.ros2.tf2_msgs_build

# Everything: the linter, then every test (slow, real-time and hardware-in-the-loop included).
# First the Cortex-M toolchain and QEMU of tests/test_embedded_qemu.py (Debian packages, installed
# only when missing and when it can: as root with apt); if they cannot be, those tests fail and
# say which tool is missing and how to install it. Then two passes: the tests that do not run
# against the wall clock, shared over the cores (up to 4 processes, pytest-xdist) as test-fast
# shares its own; then the real-time and hardware-in-the-loop tests one at a time, with the
# machine to themselves (their 1 kHz loops and the virtual chain's replies are timed). Both
# passes run whatever the first gave; the target fails if either did.
test: $(STAMP) tf2-msgs lib embedded lint
	-@bash embedded/ports/ensure_tools.sh
	@status=0; \
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -m "not realtime and not hil" \
	    -n auto --maxprocesses 4 || status=$$?; \
	$(BIN)/python -m pytest -m "realtime or hil" || status=$$?; \
	exit $$status

# The quick loop while editing: every test but those marked slow, realtime or hil (< 1 min on
# 2 cores). Its tests run on up to 4 processes (pytest-xdist), so what several of them build
# (cochlea-embedded) is built first, once. The quick loop keeps Python's bytecode and pytest's
# rewritten test modules (__pycache__/) even where PYTHONDONTWRITEBYTECODE is set: rewriting
# the assertions of every test module is half of collecting them, paid by every process.
# `make test` runs its timed tests (realtime, hil) one at a time, after the others.
test-fast: $(STAMP) tf2-msgs lib embedded
	PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest -m "not slow and not realtime and not hil" \
	    -q -n auto --maxprocesses 4

lint: $(STAMP)
	$(BIN)/ruff check cochlea tests bench setup.py

# The C kernels: build/libcochlea.so from the committed generated_c/, no Python needed.
# Warnings are errors, so none can creep into the generated code.
CC       ?= cc
CFLAGS_C ?= -O2
LIBFLAGS := -std=c99 -fPIC -Wall -Wextra -Werror
JOBS     ?= $(shell nproc 2>/dev/null || echo 2)
GEN      ?= generated_c
# A user's kernels (GEN=DIR from `cochlea-codegen --out DIR`) build into DIR/build unless BUILD
# says otherwise, so they never overwrite the shipped build/libcochlea.so or cochlea-embedded.
BUILD    ?= $(if $(filter generated_c generated_c/,$(GEN)),build,$(GEN)/build)
LIB      := $(BUILD)/libcochlea.so
C_SRC    := $(sort $(wildcard $(GEN)/*.c))
C_OBJ    := $(patsubst $(GEN)/%.c,$(BUILD)/obj/%.o,$(C_SRC))

lib:
	@$(MAKE) --no-print-directory -j$(JOBS) $(LIB) $(LANE)

$(BUILD)/obj/%.o: $(GEN)/%.c $(wildcard $(GEN)/*.h)
	@mkdir -p $(@D)
	$(CC) $(CFLAGS_C) $(LIBFLAGS) -c $< -o $@

$(LIB): $(C_OBJ)
	$(CC) -shared -o $@ $(C_OBJ) -lm

# The bus period's packet work in C, for the emulator and the bridge (cochlea/dynamixel/lane.py):
# always into build/, whatever GEN, as both look for it there; without it they work in Python.
LANE     := build/libcochlea-lane.so
LANE_SRC := cochlea/dynamixel/c/lane.c embedded/core/dxl.c

$(LANE): $(LANE_SRC) embedded/core/dxl.h
	@mkdir -p $(@D)
	$(CC) $(CFLAGS_C) $(LIBFLAGS) -Iembedded/core -shared -o $@ $(LANE_SRC)

# The embedded program, no Python: build/cochlea-embedded (double) and
# build/cochlea-embedded-float (single precision) from the portable core (embedded/core/), the
# POSIX port (embedded/posix/) and every generated scenario (generated_c/embedded/).
# See docs/embedded.md.
EMB_SRC   := $(sort $(wildcard embedded/core/*.c embedded/posix/*.c $(GEN)/embedded/*.c))
EMB_DEPS  := $(EMB_SRC) $(wildcard embedded/core/*.h embedded/posix/*.h $(GEN)/embedded/*.h)
EMB_FLAGS := -std=c99 -O2 -Wall -Wextra -Werror -pthread -Iembedded/core -Iembedded/posix \
             -I$(GEN)/embedded

embedded: $(BUILD)/cochlea-embedded $(BUILD)/cochlea-embedded-float

$(BUILD)/cochlea-embedded: $(EMB_DEPS)
	@mkdir -p $(@D)
	$(CC) $(EMB_FLAGS) $(EMB_SRC) -o $@ -lm

$(BUILD)/cochlea-embedded-float: $(EMB_DEPS)
	@mkdir -p $(@D)
	$(CC) $(EMB_FLAGS) -DCOCHLEA_FLOAT $(EMB_SRC) -o $@ -lm

# Regenerate generated_c/ from models/robots/ and codegen/kernels.toml
# (then commit it).
codegen: $(STAMP)
	$(BIN)/cochlea-codegen

# The robustness table of the four controllers (ideal, realistic, stressed plants):
# writes docs/robustness.md (about a minute).
robustness: $(STAMP)
	$(BIN)/python bench/robustness.py

# The robustness maps (cochlea-sweep, 400 samples per controller and plant): writes
# docs/robustness/NAME/ and docs/robustness_maps.md (a few minutes per map on two cores).
robustness-maps: $(STAMP)
	$(BIN)/python bench/robustness_maps.py

# The benchmark: writes bench/results.md and bench/results.json (takes a few minutes). It first
# installs the bench extra (MuJoCo, the reference of the plant step's speed) into the venv;
# `make test` and `make demo` do not need it and do not install it.
bench: $(STAMP) lib
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	$(BIN)/python bench/run.py

# A user's robot on C kernels (UR5 and a 4-DoF arm imported from URDFs): generation +
# compilation time and the as-fast run on C against CasADi and against the shipped serial study,
# in one run -> bench/user_robot.json (about 2 minutes). See docs/codegen.md.
bench-user: $(STAMP)
	$(BIN)/python bench/user_robot.py

# The embedded core's code size and worst stack per entry point, cross-compiled for a
# Cortex-M4F and aarch64 Linux with zig cc (the ziglang wheel) and for the host: writes the
# size section of docs/embedded.md and bench/embedded_size.json (about 10 s).
embedded-size: $(STAMP)
	$(BIN)/python bench/embedded_size.py

# The all-in-C simulations (embedded/sim/simulate.c): per scenario and precision, the embedded
# controller and the plant kernels in one program, build/embedded-sim/<scenario>/<precision>/
# simulate (no arguments: the whole scenario; --duration S, --log FILE). See docs/embedded.md.
embedded-sim: $(STAMP) lib
	$(BIN)/python bench/embedded_bench.py build

# The runtime's acceptance measurement: a 20 s real-time run of the serial task study
# (deadline misses below 0.5 %, same results as the as-fast run) -> bench/realtime.md.
realtime-check: $(STAMP) lib
	$(BIN)/python bench/realtime_check.py

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache

# The controller on emulated Cortex-M cores (docs/embedded.md, "Cortex-M under QEMU"): the
# replay firmware of embedded/ports/qemu_mps2/ (the period loop of a scenario on canned
# measurements, each period's command and goal currents printed in hex) for QEMU's mps2-an386
# (Cortex-M4F) and mps2-an500 (Cortex-M7), in double and in float, and the same replay built
# for the host to compare with: build/qemu/<an386|an500|host>-<double|float>/<scenario>[.elf].
# embedded/ports/ensure_tools.sh installs arm-none-eabi-gcc, newlib and qemu-system-arm when
# they are missing (as root, with apt). QEMU_INPUTS: the folder of the inputs_<scenario>.h
# headers (the canned measurements; record_inputs.py). tests/test_embedded_qemu.py runs them.
QEMU_DIR       := embedded/ports/qemu_mps2
QEMU_SCENARIOS ?= serial_task parallel_task_realistic
QEMU_INPUTS    ?= $(QEMU_DIR)
ARM_CC         ?= arm-none-eabi-gcc
HOST_CC        ?= cc
QEMU_CFLAGS    := -std=c99 -O2 -Wall -Wextra -Werror -ffp-contract=off -Iembedded/core \
                  -I$(GEN)/embedded -I$(QEMU_INPUTS) -I$(QEMU_DIR)
QEMU_CPU_an386 := -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16
QEMU_CPU_an500 := -mcpu=cortex-m7 -mthumb -mfloat-abi=hard -mfpu=fpv5-d16
QEMU_LDFLAGS   := -T $(QEMU_DIR)/mps2.ld -nostartfiles --specs=nano.specs --specs=nosys.specs \
                  -Wl,--gc-sections
QEMU_PREC_double :=
QEMU_PREC_float  := -DCOCHLEA_FLOAT
QEMU_CORE      := $(sort $(wildcard embedded/core/*.c))
QEMU_DEPS       = $(QEMU_CORE) $(wildcard embedded/core/*.h $(QEMU_DIR)/*.c $(QEMU_DIR)/*.h) \
                  $(QEMU_DIR)/mps2.ld $(GEN)/embedded/$(1).c $(GEN)/embedded/$(1).h \
                  $(GEN)/embedded/$(1)_scenario.c $(QEMU_INPUTS)/inputs_$(1).h
QEMU_SOURCES    = $(QEMU_CORE) $(GEN)/embedded/$(1).c $(GEN)/embedded/$(1)_scenario.c \
                  $(QEMU_DIR)/replay.c -DREPLAY_SCENARIO=$(1) '-DREPLAY_INPUTS=<inputs_$(1).h>'

define QEMU_RULES
$(BUILD)/qemu/an386-$(2)/$(1).elf $(BUILD)/qemu/an500-$(2)/$(1).elf: $(BUILD)/qemu/%-$(2)/$(1).elf: $(call QEMU_DEPS,$(1))
	@mkdir -p $$(@D)
	$(ARM_CC) $(QEMU_CFLAGS) $$(QEMU_CPU_$$*) $(QEMU_PREC_$(2)) $(call QEMU_SOURCES,$(1)) \
	    $(QEMU_DIR)/port_mps2.c $(QEMU_LDFLAGS) -o $$@.partial -lm && mv $$@.partial $$@
$(BUILD)/qemu/host-$(2)/$(1): $(call QEMU_DEPS,$(1))
	@mkdir -p $$(@D)
	$(HOST_CC) $(QEMU_CFLAGS) $(QEMU_PREC_$(2)) $(call QEMU_SOURCES,$(1)) \
	    $(QEMU_DIR)/port_host.c -o $$@.partial -lm && mv $$@.partial $$@
endef
$(foreach s,$(QEMU_SCENARIOS),$(foreach p,double float,$(eval $(call QEMU_RULES,$(s),$(p)))))
QEMU_OUT := $(foreach s,$(QEMU_SCENARIOS),$(foreach p,double float,\
              $(BUILD)/qemu/an386-$(p)/$(s).elf $(BUILD)/qemu/an500-$(p)/$(s).elf \
              $(BUILD)/qemu/host-$(p)/$(s)))

.PHONY: qemu-firmware
qemu-firmware:
	@bash embedded/ports/ensure_tools.sh
	@$(MAKE) --no-print-directory -j$(JOBS) $(QEMU_OUT)

# The STM32F4 board port (embedded/ports/stm32f4/, docs/embedded.md "STM32F4 port"): one
# scenario's real-time loop over the Dynamixel bus on USART1, register level, for an
# STM32F405/407 (Cortex-M4F, 168 MHz), float (the FPU's precision) and double:
# build/stm32f4/<float|double>/cochlea-stm32f4.elf (and .bin). It also runs on QEMU's
# netduinoplus2 machine (tests/test_embedded_stm32.py). Compiled in: STM32_SCENARIO,
# STM32_DURATION (s, 0: the scenario's), STM32_WATCHDOG_MISSES, STM32_WATCHDOG_ERRORS,
# STM32_BAUD, STM32_READ_TIMEOUT_US (a period's SYNC_READ reply), STM32_RATE (Hz, 0: the
# scenario's; cochlea-run's --rate), STM32_BUS_WATCHDOG_MS (the motors' Bus Watchdog, 20..2540),
# STM32_TIMER_HZ (TIM2's clock: 84 MHz on a board, 1000000000 under QEMU, whose model counts at
# 1 GHz), STM32_TIMER_START (TIM2's first count: a test puts a wrap inside the run),
# STM32_STREAM_EVERY (every N-th period's row goes out on USART3's row stream) and
# STM32_STREAM_BAUD (its rate; `cochlea-embedded-host` reads it: docs/embedded.md "The row
# stream").
STM32_DIR              := embedded/ports/stm32f4
# What the board ports share (the run, the console's report, the row stream's framing).
PORTS_COMMON           := embedded/ports/common
PORTS_COMMON_SRC       := $(sort $(wildcard $(PORTS_COMMON)/*.c))
STM32_SCENARIO         ?= serial_joint
STM32_DURATION         ?= 0
STM32_WATCHDOG_MISSES  ?= 20
STM32_WATCHDOG_ERRORS  ?= 5
STM32_BAUD             ?= 4000000
STM32_READ_TIMEOUT_US  ?= 5000
STM32_RATE             ?= 0
STM32_BUS_WATCHDOG_MS  ?= 100
STM32_TIMER_HZ         ?= 84000000
STM32_TIMER_START      ?= 0
STM32_STREAM_EVERY     ?= 10
STM32_STREAM_BAUD      ?= 921600
# A prismatic joint (the parallel robot's slider) moves only counted from a homing record,
# compiled in (a board has no file system): STM32_HOMING_RECORD=FILE, the record cochlea-dxl
# home wrote, checked at build time against STM32_HOMING_SCENARIO (default STM32_SCENARIO; a
# user's scenario file for GEN=DIR) by cochlea.dynamixel.homing_firmware (the venv's Python);
# the firmware reads the token from the motor at its start (docs/embedded.md, "Homing").
STM32_HOMING_RECORD    ?=
STM32_HOMING_SCENARIO  ?= $(STM32_SCENARIO)
STM32_HOMING_H         := $(BUILD)/stm32f4/homing/homing_record.h
STM32_HOMING_FLAGS     := $(if $(STM32_HOMING_RECORD),-DSTM32_HOMED=1 -I$(dir $(STM32_HOMING_H)))
STM32_CPU      := -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16
STM32_CFLAGS   := -std=c99 -O2 -Wall -Wextra -Werror -ffp-contract=off -ffunction-sections \
                  -fdata-sections -fstack-usage -Iembedded/core -I$(GEN)/embedded -I$(STM32_DIR) \
                  -I$(PORTS_COMMON) \
                  -DSTM32_SCENARIO=$(STM32_SCENARIO) -DSTM32_DURATION_S=$(STM32_DURATION) \
                  -DSTM32_WATCHDOG_MISSES=$(STM32_WATCHDOG_MISSES) \
                  -DSTM32_WATCHDOG_ERRORS=$(STM32_WATCHDOG_ERRORS) -DSTM32_BAUD=$(STM32_BAUD)u \
                  -DSTM32_READ_TIMEOUT_NS=$(STM32_READ_TIMEOUT_US)000 -DSTM32_RATE_HZ=$(STM32_RATE) \
                  -DSTM32_BUS_WATCHDOG_MS=$(STM32_BUS_WATCHDOG_MS) -DSTM32_TIMER_HZ=$(STM32_TIMER_HZ)u \
                  -DSTM32_TIMER_START=$(STM32_TIMER_START)u \
                  -DSTM32_STREAM_EVERY=$(STM32_STREAM_EVERY)u \
                  -DSTM32_STREAM_BAUD=$(STM32_STREAM_BAUD)u $(STM32_HOMING_FLAGS)
STM32_LDFLAGS  := -T $(STM32_DIR)/stm32f405.ld -nostartfiles --specs=nano.specs \
                  --specs=nosys.specs -Wl,--gc-sections
STM32_SOURCES  := $(sort $(wildcard embedded/core/*.c)) $(GEN)/embedded/$(STM32_SCENARIO).c \
                  $(GEN)/embedded/$(STM32_SCENARIO)_scenario.c $(sort $(wildcard $(STM32_DIR)/*.c)) \
                  $(PORTS_COMMON_SRC)
STM32_DEPS     := $(STM32_SOURCES) $(wildcard embedded/core/*.h $(STM32_DIR)/*.h) \
                  $(wildcard $(PORTS_COMMON)/*.h) \
                  $(STM32_DIR)/stm32f405.ld $(GEN)/embedded/$(STM32_SCENARIO).h Makefile
# The compiled-in settings: a change rebuilds (the file changes only when they do).
STM32_CONFIG   := $(STM32_CFLAGS) $(STM32_CPU) $(ARM_CC) $(STM32_HOMING_RECORD) \
                  $(STM32_HOMING_SCENARIO)
STM32_DEPS     += $(BUILD)/stm32f4/config.txt $(if $(STM32_HOMING_RECORD),$(STM32_HOMING_H))
STM32_PREC_double :=
STM32_PREC_float  := -DCOCHLEA_FLOAT

$(BUILD)/stm32f4/%/cochlea-stm32f4.elf: $(STM32_DEPS)
	@mkdir -p $(@D)
	$(ARM_CC) $(STM32_CFLAGS) $(STM32_CPU) $(STM32_PREC_$*) $(STM32_SOURCES) $(STM32_LDFLAGS) \
	    -Wl,-Map,$(@D)/cochlea-stm32f4.map -o $@.partial -lm
	arm-none-eabi-objcopy -O binary $@.partial $(@D)/cochlea-stm32f4.bin
	mv $@.partial $@

$(BUILD)/stm32f4/config.txt: stm32-config-check
	@mkdir -p $(@D)
	@echo '$(STM32_CONFIG)' | cmp -s - $@ || echo '$(STM32_CONFIG)' > $@

$(STM32_HOMING_H): $(wildcard $(STM32_HOMING_RECORD)) $(BUILD)/stm32f4/config.txt $(STAMP)
	@$(BIN)/python -m cochlea.dynamixel.homing_firmware --scenario $(STM32_HOMING_SCENARIO) \
	    --record $(STM32_HOMING_RECORD) --out $@

# The row stream (docs/embedded.md, "The row stream"): the frame codec, cochlea-embedded-host
# on made streams, and the firmware on QEMU's netduinoplus2 streaming to it.
.PHONY: stm32-stream-test
stm32-stream-test: $(STAMP) lib
	-@bash embedded/ports/ensure_tools.sh
	$(BIN)/python -m pytest -q tests/test_embedded_stream.py

.PHONY: stm32-firmware stm32-config-check
stm32-config-check:
stm32-firmware:
	$(if $(wildcard $(GEN)/embedded/$(STM32_SCENARIO)_scenario.c),,$(error stm32-firmware: unknown \
	    scenario STM32_SCENARIO=$(STM32_SCENARIO); one of: $(patsubst \
	    $(GEN)/embedded/%_scenario.c,%,$(wildcard $(GEN)/embedded/*_scenario.c))))
	@bash embedded/ports/ensure_tools.sh
	@$(MAKE) --no-print-directory $(BUILD)/stm32f4/float/cochlea-stm32f4.elf \
	    $(BUILD)/stm32f4/double/cochlea-stm32f4.elf

# The OpenCR board port (embedded/ports/opencr/, docs/embedded.md "OpenCR (STM32F746) port"):
# the same firmware as the STM32F4 port's (embedded/ports/common/) on ROBOTIS's OpenCR, an
# STM32F746ZG (Cortex-M7, double-precision FPU, 216 MHz): the Dynamixel bus on USART3 with DMA
# receive, its direction pin (PC9) and power switch (PF15), float and double:
# build/opencr/<float|double>/cochlea-opencr.elf (and .bin, .map, the compiler's .su files),
# then each image's size and worst stack (embedded/ports/common/stack_report.py). No emulator
# models this chip (QEMU 7.2 has no STM32F7 machine): tests/test_embedded_opencr.py checks the
# build, the memory map and the HAL against a register model on the host. Compiled in: the
# STM32F4 port's settings under OPENCR_ names (OPENCR_SCENARIO, OPENCR_DURATION, ...), and
# OPENCR_POWER_SETTLE_MS (the motors' boot time after the power switch closes, ROBOTIS's 1 s).
# OPENCR_LOAD=swd (default) links at 0x08000000 for an SWD probe or DFU, replacing OpenCR's
# bootloader, into build/opencr/; OPENCR_LOAD=bootloader links at 0x08040000 for ROBOTIS's
# bootloader and its opencr_ld, into build/opencr-bootloader/.
OPENCR_DIR              := embedded/ports/opencr
OPENCR_LOAD             ?= swd
OPENCR_LD_swd           := stm32f746.ld
OPENCR_LD_bootloader    := stm32f746_bootloader.ld
OPENCR_OUT_swd          := opencr
OPENCR_OUT_bootloader   := opencr-bootloader
OPENCR_LD               := $(OPENCR_LD_$(OPENCR_LOAD))
OPENCR_OUT              := $(BUILD)/$(OPENCR_OUT_$(OPENCR_LOAD))
OPENCR_SCENARIO         ?= serial_joint
OPENCR_DURATION         ?= 0
OPENCR_WATCHDOG_MISSES  ?= 20
OPENCR_WATCHDOG_ERRORS  ?= 5
OPENCR_BAUD             ?= 4000000
OPENCR_READ_TIMEOUT_US  ?= 5000
OPENCR_RATE             ?= 0
OPENCR_BUS_WATCHDOG_MS  ?= 100
OPENCR_STREAM_EVERY     ?= 10
OPENCR_STREAM_BAUD      ?= 921600
OPENCR_POWER_SETTLE_MS  ?= 1000
OPENCR_HOMING_RECORD    ?=
OPENCR_HOMING_SCENARIO  ?= $(OPENCR_SCENARIO)
OPENCR_HOMING_H         := $(OPENCR_OUT)/homing/homing_record.h
OPENCR_HOMING_FLAGS     := $(if $(OPENCR_HOMING_RECORD),-DSTM32_HOMED=1 \
                           -I$(dir $(OPENCR_HOMING_H)))
OPENCR_CPU     := -mcpu=cortex-m7 -mthumb -mfloat-abi=hard -mfpu=fpv5-d16
OPENCR_CFLAGS  := -std=c99 -O2 -Wall -Wextra -Werror -ffp-contract=off -ffunction-sections \
                  -fdata-sections -fstack-usage -Iembedded/core -I$(GEN)/embedded -I$(OPENCR_DIR) \
                  -I$(PORTS_COMMON) \
                  -DSTM32_SCENARIO=$(OPENCR_SCENARIO) -DSTM32_DURATION_S=$(OPENCR_DURATION) \
                  -DSTM32_WATCHDOG_MISSES=$(OPENCR_WATCHDOG_MISSES) \
                  -DSTM32_WATCHDOG_ERRORS=$(OPENCR_WATCHDOG_ERRORS) -DSTM32_BAUD=$(OPENCR_BAUD)u \
                  -DSTM32_READ_TIMEOUT_NS=$(OPENCR_READ_TIMEOUT_US)000 \
                  -DSTM32_RATE_HZ=$(OPENCR_RATE) \
                  -DSTM32_BUS_WATCHDOG_MS=$(OPENCR_BUS_WATCHDOG_MS) \
                  -DSTM32_STREAM_EVERY=$(OPENCR_STREAM_EVERY)u \
                  -DSTM32_STREAM_BAUD=$(OPENCR_STREAM_BAUD)u \
                  -DOPENCR_POWER_SETTLE_MS=$(OPENCR_POWER_SETTLE_MS)u $(OPENCR_HOMING_FLAGS)
OPENCR_LDFLAGS := -L $(OPENCR_DIR) -T $(OPENCR_DIR)/$(OPENCR_LD) -nostartfiles --specs=nano.specs \
                  --specs=nosys.specs -Wl,--gc-sections
OPENCR_SOURCES := $(sort $(wildcard embedded/core/*.c)) $(GEN)/embedded/$(OPENCR_SCENARIO).c \
                  $(GEN)/embedded/$(OPENCR_SCENARIO)_scenario.c \
                  $(sort $(wildcard $(OPENCR_DIR)/*.c)) $(PORTS_COMMON_SRC)
OPENCR_DEPS    := $(OPENCR_SOURCES) $(wildcard embedded/core/*.h $(OPENCR_DIR)/*.h) \
                  $(wildcard $(PORTS_COMMON)/*.h) $(wildcard $(OPENCR_DIR)/*.ld) \
                  $(GEN)/embedded/$(OPENCR_SCENARIO).h Makefile $(OPENCR_OUT)/config.txt \
                  $(if $(OPENCR_HOMING_RECORD),$(OPENCR_HOMING_H))
OPENCR_CONFIG  := $(OPENCR_CFLAGS) $(OPENCR_CPU) $(ARM_CC) $(OPENCR_LD) $(OPENCR_HOMING_RECORD) \
                  $(OPENCR_HOMING_SCENARIO)
OPENCR_PREC_double :=
OPENCR_PREC_float  := -DCOCHLEA_FLOAT

$(OPENCR_OUT)/%/cochlea-opencr.elf: $(OPENCR_DEPS)
	@mkdir -p $(@D)
	cd $(@D) && rm -f *.su
	$(ARM_CC) $(OPENCR_CFLAGS) $(OPENCR_CPU) $(OPENCR_PREC_$*) $(OPENCR_SOURCES) \
	    $(OPENCR_LDFLAGS) -Wl,-Map,$(@D)/cochlea-opencr.map -o $@.partial -lm
	arm-none-eabi-objcopy -O binary $@.partial $(@D)/cochlea-opencr.bin
	mv $@.partial $@

$(OPENCR_OUT)/config.txt: opencr-config-check
	@mkdir -p $(@D)
	@echo '$(OPENCR_CONFIG)' | cmp -s - $@ || echo '$(OPENCR_CONFIG)' > $@

$(OPENCR_HOMING_H): $(wildcard $(OPENCR_HOMING_RECORD)) $(OPENCR_OUT)/config.txt $(STAMP)
	@$(BIN)/python -m cochlea.dynamixel.homing_firmware --scenario $(OPENCR_HOMING_SCENARIO) \
	    --record $(OPENCR_HOMING_RECORD) --out $@

.PHONY: opencr-firmware opencr-config-check
opencr-config-check:
opencr-firmware:
	$(if $(wildcard $(GEN)/embedded/$(OPENCR_SCENARIO)_scenario.c),,$(error opencr-firmware: \
	    unknown scenario OPENCR_SCENARIO=$(OPENCR_SCENARIO); one of: $(patsubst \
	    $(GEN)/embedded/%_scenario.c,%,$(wildcard $(GEN)/embedded/*_scenario.c))))
	$(if $(OPENCR_LD),,$(error opencr-firmware: OPENCR_LOAD=$(OPENCR_LOAD) is not swd or \
	    bootloader))
	@bash embedded/ports/ensure_tools.sh
	@$(MAKE) --no-print-directory $(OPENCR_OUT)/float/cochlea-opencr.elf \
	    $(OPENCR_OUT)/double/cochlea-opencr.elf
	@python3 $(PORTS_COMMON)/stack_report.py $(OPENCR_OUT)/float/cochlea-opencr.elf \
	    $(OPENCR_OUT)/double/cochlea-opencr.elf
