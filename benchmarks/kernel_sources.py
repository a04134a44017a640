"""Where a study program's fused kernels come from: counts by jaxloc module and line.

    python benchmarks/kernel_sources.py [--strategy sequential] [--top 40] [--methods ...]

Compiles one study chunk program (as `jaxloc table1` does) and attributes each fused
kernel of the optimized program to the source line in its metadata (the line of jaxloc
code that produced the fusion's root operation), then prints the lines and modules with
the most kernels. XLA:CPU compiles each fused kernel with LLVM (~15 ms each here), so this
is where compile time goes.
"""

import argparse
import collections
import os
import re


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--strategy", default="sequential")
    parser.add_argument("--methods", default="paper,robust,refined")
    parser.add_argument("--top", type=int, default=40)
    parser.add_argument("--devices", type=int, default=2)
    args = parser.parse_args()
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={args.devices}"
    )
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_compilation_cache_dir", None)
    import jaxloc
    import jaxloc._study.engine as engine

    scenario = jaxloc.Scenario.paper(args.strategy)
    chunk = engine.balanced_chunk_size(10_000)
    methods = tuple(args.methods.split(","))
    lowered = engine._run_chunk.lower(*engine._chunk_inputs(scenario, 0, 0, chunk, methods))
    text = lowered.compile().compiled.as_text()
    frames = _frames(text)
    by_line, by_module = collections.Counter(), collections.Counter()
    total = 0
    for line in text.splitlines():
        if " fusion(" not in line:
            continue
        total += 1
        m = re.search(r"stack_frame_id=(\d+)", line)
        where = frames(int(m.group(1))) if m else None
        if where is None:
            op = re.search(r'op_name="([^"]+)"', line)
            where = "(no jaxloc frame) " + (op.group(1)[-60:] if op else "")
        by_line[where] += 1
        by_module[where.split(":")[0] if not where.startswith("(") else "(no jaxloc frame)"] += 1
    print(f"{args.strategy}: {total} fused kernels")
    print("\nBy module:")
    for name, n in by_module.most_common(args.top):
        print(f"{n:6d}  {name}")
    print("\nBy line:")
    for name, n in by_line.most_common(args.top):
        print(f"{n:6d}  {name}")


def _table(lines, name):
    """`{id: value}` of one of the HLO text's source tables (`FileNames`, ...)."""
    out, inside = {}, False
    for line in lines:
        if line == name:
            inside = True
            continue
        if inside:
            m = re.match(r"(\d+) (.*)", line)
            if not m:
                break
            out[int(m.group(1))] = m.group(2)
    return out


def _frames(text):
    """A function from a stack frame id to its innermost jaxloc `module:line (function)`."""
    lines = text.splitlines()[:200_000]
    files = {k: v.strip('"') for k, v in _table(lines, "FileNames").items()}
    functions = {k: v.strip('"') for k, v in _table(lines, "FunctionNames").items()}
    locations = {}
    for k, v in _table(lines, "FileLocations").items():
        f = re.search(r"file_name_id=(\d+) function_name_id=(\d+) line=(\d+)", v)
        locations[k] = (files[int(f.group(1))], functions[int(f.group(2))], int(f.group(3)))
    stack = {}
    for k, v in _table(lines, "StackFrames").items():
        f = re.search(r"file_location_id=(\d+) parent_frame_id=(\d+)", v)
        stack[k] = (int(f.group(1)), int(f.group(2)))

    def where(frame_id):
        seen = set()
        while frame_id in stack and frame_id not in seen:
            seen.add(frame_id)
            loc, parent = stack[frame_id]
            path, fn, line = locations[loc]
            if "/jaxloc/" in path:
                return f"{path.split('/jaxloc/')[-1]}:{line} ({fn})"
            frame_id = parent
        return None

    return where


if __name__ == "__main__":
    main()
