"""Register spills of the laned string kernels (issue 13 item 5): instructions and stack references
of each compiled kernel and of each of its loops.

Run:  python benchmarks/probe_lane_spills.py

Compiles ``integrate_string_lanes_adjoint`` (``kernels/string_step_adjoint_lanes``) and the laned
step with and without ``keep`` (``kernels/string_step_lanes``), every effect on, ``K = 4``, into a
fresh kernel cache (a temporary folder, so the object file is the one just built), disassembles
each kernel's ``cpu_forward`` function (``objdump -d``) and counts its instructions and those that
address the stack (``(%rsp)`` or ``(%rbp)``: register spills and reloads, and the kernel's arguments),
in the whole function and in each loop (the instructions from a loop head to its farthest backward
jump; loops of at least 200 instructions that hold no other such loop). Warp builds each kernel
twice (its CPU dispatch is a template of two instances), so most loops are listed twice. In the
adjoint the two largest are the forward substitution and the back substitution's rows between the
first and the last (one row of ``K`` particles per iteration). Nothing here is used by the
simulator; the findings are in ``docs/lanes_status.md``, "Fewer instructions in the laned adjoint".
"""

from __future__ import annotations

import glob
import re
import subprocess
import tempfile

import warp as wp

from dmarionette.kernels.string_step_adjoint_lanes import string_step_adjoint_lanes_kernel
from dmarionette.kernels.string_step_lanes import integrate_string_lanes_kernel

MIN_LOOP = 200


def _instructions(kernel) -> list[tuple[int, str, str]]:
    """``(address, mnemonic, operands)`` of the kernel's compiled ``cpu_forward`` function."""
    wp.load_module(kernel.module, device="cpu")
    name = kernel.module.get_module_identifier().rsplit("_", 1)[0]
    (obj,) = glob.glob(f"{wp.config.kernel_cache_dir}/{name}_*/*.o")
    text = subprocess.run(["objdump", "-d", "--no-show-raw-insn", obj], capture_output=True, text=True,
                          check=True).stdout
    (function,) = [f for f in re.split(r"\n(?=[0-9a-f]+ <)", text) if "cpu_forward>:" in f.split("\n", 1)[0]]
    rows = [re.match(r"\s+([0-9a-f]+):\s+(\S+)\s*(.*)", line) for line in function.split("\n")[1:]]
    return [(int(m.group(1), 16), m.group(2), m.group(3)) for m in rows if m]


def _stack(instructions) -> int:
    return sum(1 for _a, _op, operands in instructions if "(%rsp)" in operands or "(%rbp)" in operands)


def _loops(instructions) -> list[tuple[int, int]]:
    """``(first, last)`` index of each loop: a loop head and its farthest backward jump."""
    index = {a: i for i, (a, _op, _operands) in enumerate(instructions)}
    loops: dict[int, int] = {}
    for i, (a, op, operands) in enumerate(instructions):
        target = re.match(r"([0-9a-f]+) <", operands)
        if op.startswith("j") and target and int(target.group(1), 16) < a and int(target.group(1), 16) in index:
            head = index[int(target.group(1), 16)]
            loops[head] = max(loops.get(head, 0), i)
    return sorted(loops.items())


def main() -> None:
    wp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="probe_lane_spills_")
    wp.config.quiet = True
    wp.init()
    effects = (True,) * 5
    kernels = {
        "laned adjoint": string_step_adjoint_lanes_kernel(effects),
        "laned step, keep": integrate_string_lanes_kernel(effects, keep=True),
        "laned step": integrate_string_lanes_kernel(effects),
    }
    for name, kernel in kernels.items():
        instructions = _instructions(kernel)
        print(f"{name}: {len(instructions)} instructions, {_stack(instructions)} stack references")
        loops = [(first, last) for first, last in _loops(instructions) if last - first >= MIN_LOOP]
        for first, last in loops:
            body = instructions[first:last + 1]
            if not any(first < other <= last for other, _last in loops):  # not a loop around a listed one
                print(f"  loop at {instructions[first][0]:#x}: {len(body)} instructions, "
                      f"{_stack(body)} stack references")


if __name__ == "__main__":
    main()
