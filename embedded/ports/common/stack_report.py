"""Size and worst stack of a linked board firmware (``make opencr-firmware`` runs it).

Usage: ``python3 stack_report.py ELF [ELF ...]``: for each image, one line of its sizes
(``arm-none-eabi-size``'s text, data, bss and the other allocated sections) and one of its
worst stack. Standard library only (the board's build needs no virtual environment).

The worst stack is static: each function's frame from the compiler's ``-fstack-usage`` files
(written beside the image: ``<image>.partial-<source>.su``) and the deepest chain of calls
through the image's call graph, read from its disassembly (``bl`` and ``b.w`` to a symbol).
An indirect call (``blx rN``, or a tail call ``bx rN``: the HAL's callbacks, the backend, the
loop's row and watchdog hooks, the tick hook, the scenario's controller) may reach any
function whose address the image holds outside the vector table (a word equal to its Thumb
address), a superset of the real targets: the bound errs high. The thread's chain starts at
Reset_Handler; every interrupt priority level in use (bus, SysTick, stream; faults above all)
adds its deepest handler's chain and the core's exception frame with the FPU's registers (104
bytes). Functions with no ``.su`` entry (newlib's, libgcc's helpers) count 0 and are named. A
cycle in the graph is reported, not followed round.
"""

from __future__ import annotations

import re
import subprocess
import sys
from functools import cache
from pathlib import Path

#: Interrupt handlers by priority level (the NVIC byte each port sets; faults highest).
LEVELS = (("fault", ("Fault_Handler",)),
          ("bus", ("USART3_IRQHandler", "DMA1_Stream1_IRQHandler", "USART1_IRQHandler")),
          ("systick", ("SysTick_Handler",)),
          ("stream", ("USART2_IRQHandler", "USART3_IRQHandler_stream")))
#: The Cortex-M's exception frame with the FPU's registers (lazy stacking reserves them).
EXCEPTION_FRAME = 104


def run(*args: str) -> str:
    return subprocess.run(args, capture_output=True, text=True, check=True).stdout


def frames(elf: Path) -> dict[str, int]:
    """Function -> its frame (bytes), the largest when two static functions share a name."""
    out: dict[str, int] = {}
    for su in elf.parent.glob(f"{elf.name}*.su"):
        for line in su.read_text().splitlines():
            parts = line.split("\t")
            if len(parts) >= 2 and parts[1].isdigit():
                name = parts[0].rsplit(":", 1)[-1]
                out[name] = max(out.get(name, 0), int(parts[1]))
    return out


def functions(elf: Path) -> dict[int, str]:
    """Address (without the Thumb bit) -> function name."""
    out = {}
    for line in run("arm-none-eabi-nm", "--defined-only", str(elf)).splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[1] in "Tt":
            out[int(parts[0], 16) & ~1] = parts[2]
    return out


def call_graph(elf: Path) -> tuple[dict[str, set[str]], set[str]]:
    """Direct callees of each function, and the functions that call through a register."""
    callees: dict[str, set[str]] = {}
    indirect: set[str] = set()
    current = None
    for line in run("arm-none-eabi-objdump", "-d", "--no-show-raw-insn", str(elf)).splitlines():
        head = re.match(r"^[0-9a-f]+ <([^>]+)>:$", line)
        if head:
            current = head.group(1)
            callees.setdefault(current, set())
            continue
        if current is None:
            continue
        call = re.search(r"\t(bl|b\.w|b)\s+[0-9a-f]+ <([^>+]+)>", line)
        if call and call.group(2) != current:
            callees[current].add(call.group(2))
        elif re.search(r"\t(blx\s+r\d+|bx\s+(r\d+|ip))", line):  # a call, or a tail call
            indirect.add(current)
    return callees, indirect


def address_taken(elf: Path, names: dict[int, str]) -> set[str]:
    """Functions whose Thumb address is a word of the image outside the vector table."""
    image = elf.with_suffix(".bin").read_bytes()
    table = 4 * (16 + 98)
    taken = set()
    for at in range(table, len(image) - 3, 2):
        word = int.from_bytes(image[at:at + 4], "little")
        if word & 1 and (word & ~1) in names and (word & ~1) >= 0x08000000:
            taken.add(names[word & ~1])
    return taken


def report(elf: Path) -> tuple[str, str]:
    sizes = run("arm-none-eabi-size", "-A", str(elf))
    sections = {m[0]: int(m[1]) for m in re.findall(r"^(\.\w+)\s+(\d+)", sizes, re.M)}
    size_line = (f"{elf}: text {sections.get('.text', 0)} B, data {sections.get('.data', 0)} B, "
                 f"bss {sections.get('.bss', 0)} B"
                 + "".join(f", {k[1:]} {v} B" for k, v in sections.items()
                           if k not in (".text", ".data", ".bss", ".ARM.exidx", ".comment",
                                        ".ARM.attributes") and not k.startswith(".debug")))
    frame = frames(elf)
    names = functions(elf)
    callees, indirect = call_graph(elf)
    handlers = {h for _, hs in LEVELS for h in hs} | {"Reset_Handler", "Default_Handler"}
    pointer_targets = address_taken(elf, names) - handlers
    unknown: set[str] = set()
    cycles: set[str] = set()

    def edges(f: str) -> set[str]:
        return callees.get(f, set()) | (pointer_targets if f in indirect else set())

    active: set[str] = set()

    @cache
    def deepest(f: str) -> int:
        if f not in frame:
            unknown.add(f)
        if f in active:
            cycles.add(f)
            return 0
        active.add(f)
        below = max((deepest(g) for g in edges(f)), default=0)
        active.discard(f)
        return frame.get(f, 0) + below

    thread = deepest("Reset_Handler")
    total, parts = thread, [f"thread {thread}"]
    for level, hs in LEVELS:
        present = [h for h in hs if h in callees]
        if present:
            worst = max(deepest(h) for h in present)
            total += worst + EXCEPTION_FRAME
            parts.append(f"{level} {worst}+{EXCEPTION_FRAME}")
    unknown_named = sorted(u for u in unknown if not u.startswith("$"))
    stack_line = (f"{elf}: worst stack {total} B (static bound: {', '.join(parts)}); "
                  f"{len(pointer_targets)} functions reachable through pointers; "
                  f"no frame known for {len(unknown_named)} (counted 0): "
                  f"{', '.join(unknown_named[:8])}{' ...' if len(unknown_named) > 8 else ''}"
                  + (f"; cycles cut at {', '.join(sorted(cycles))}" if cycles else ""))
    return size_line, stack_line


def main(argv: list[str]) -> int:
    if not argv:
        print("usage: stack_report.py ELF [ELF ...]", file=sys.stderr)
        return 2
    for name in argv:
        elf = Path(name)
        if not elf.is_file() or not elf.with_suffix(".bin").is_file():
            print(f"stack_report: no image {elf} (and its .bin)", file=sys.stderr)
            return 2
        for line in report(elf):
            print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
