"""What a tracker's compiled program is made of, and how long it takes to compile (issue 21's
cold start): the program is compiled once, without the persistent cache, and its fused kernels
(each one a function that XLA's CPU back end generates and LLVM compiles) are attributed to
the innermost ``jaxmocap`` source function of their stack trace.

    python -m benchmarks.compile_kernels pf              # stereo filter step, N = 1000
    python -m benchmarks.compile_kernels shirt           # colour-shirt step, demo set-up
    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python -m benchmarks.compile_kernels shirt

``pf`` compiles ``stereo_pf.filter_step`` with ``stereo_pf.COMPILER_OPTIONS`` (as
``init_top_level`` and ``run_top_level`` are); ``--default`` with XLA's defaults. ``shirt``
compiles ``shirt.step`` on ``jaxmocap demo``'s set-up (2 x 320x240, 3,000-pose database).
Compile times on this machine drift by tens of per cent: compare only alternated runs, each
in its own process.
"""

from __future__ import annotations

import argparse
import collections
import json
import re
import time


def _table(lines: list[str], name: str) -> dict[int, str]:
    out: dict[int, str] = {}
    if name not in lines:
        return out
    for line in lines[lines.index(name) + 1:]:
        if not line.strip():
            break
        k, v = line.split(" ", 1)
        out[int(k)] = v
    return out


class HloFrames:
    """The stack frames in a compiled HLO text's metadata (its FileNames, FunctionNames,
    FileLocations and StackFrames tables) and each instruction's frame."""

    def __init__(self, hlo: str):
        lines = hlo.split("\n")
        self.files = {k: v.strip('"') for k, v in _table(lines, "FileNames").items()}
        self.funcs = {k: v.strip('"') for k, v in _table(lines, "FunctionNames").items()}
        self.locs = {k: dict(re.findall(r"(\w+)=(\d+)", v))
                     for k, v in _table(lines, "FileLocations").items()}  # fmt: skip
        self.frames = {}
        for k, v in _table(lines, "StackFrames").items():
            d = dict(re.findall(r"(\w+)=(\d+)", v))
            self.frames[k] = (int(d["file_location_id"]), int(d.get("parent_frame_id", 0)))
        self.op_frame = {m.group(1): int(m.group(2)) for m in re.finditer(
            r"\n\s*(?:ROOT )?%?([\w.\-]+) = [^\n]*?stack_frame_id=(\d+)", hlo)}  # fmt: skip

    def chain(self, fid: int) -> list[tuple[str, str, bool]]:
        """(file, function, inside jaxmocap) from frame ``fid`` outwards; files inside
        ``jaxmocap`` relative to the package, others by their last two path parts."""
        out, seen = [], set()
        while fid and fid not in seen and fid in self.frames:
            seen.add(fid)
            loc, fid = self.frames[fid]
            d = self.locs[loc]
            path = self.files[int(d["file_name_id"])]
            ours = "/jaxmocap/" in path and "/site-packages/" not in path
            f = path.rsplit("/jaxmocap/", 1)[1] if ours else "/".join(path.split("/")[-2:])
            out.append((f, self.funcs[int(d["function_name_id"])], ours))
        return out


def attribute(hlo: str) -> dict[str, tuple[int, int]]:
    """{source function: (fused kernels, instructions in them)} of a compiled HLO text."""
    hf = HloFrames(hlo)

    def source(fid: int) -> str:
        return next((f"{f}:{fn}" for f, fn, ours in hf.chain(fid) if ours), "(outside jaxmocap)")

    sizes = {m.group(1).lstrip("%"): m.group(2).count("\n") + 1
             for m in re.finditer(r"\n(%?[\w.\-]+) \([^\n]*\{\n(.*?)\n\}", hlo, re.S)}
    kernels: collections.Counter = collections.Counter()
    instrs: collections.Counter = collections.Counter()
    for m in re.finditer(r" fusion\([^\n]*?calls=%?([\w.\-]+)[^\n]*?stack_frame_id=(\d+)", hlo):
        key = source(int(m.group(2)))
        kernels[key] += 1
        instrs[key] += sizes.get(m.group(1), 0)
    return {k: (kernels[k], instrs[k]) for k, _ in instrs.most_common()}


def _pf(default: bool):
    import equinox as eqx
    import jax

    from jaxmocap.segment import HSVInterval, SegmentParams
    from jaxmocap.synth import SceneConfig, render_sequence
    from jaxmocap.trackers import stereo_pf as sp

    seq = render_sequence(SceneConfig(clip="humanoid3d_punch", rig="stereo", garment="single",
                                      background="plain", n_frames=4, noise_sigma=0.01, seed=0),
                          progress=False)
    params = sp.make_params(
        list(seq.cameras),
        images=sp.Images(segment=SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV))),
    )
    obs = sp.observe_sequence(params, seq.frames)
    first = jax.tree.map(lambda a: a[sp.anchor_frame(obs)], obs)
    state, _ = sp.init(params, jax.random.key(0), first)
    if default:
        return lambda: sp.filter_step.lower(params, state, first)
    step = eqx.filter_jit(sp.filter_step, compiler_options=sp.COMPILER_OPTIONS)
    return lambda: step.lower(params, state, first)


def _shirt():
    import jax.numpy as jnp

    from jaxmocap.synth import SceneConfig, render_sequence
    from jaxmocap.trackers import shirt
    from jaxmocap.trackers.shirt import export as demo
    from jaxmocap.trackers.shirt import sequence as shirt_sequence

    seq = render_sequence(
        SceneConfig(
            clip=demo.DEMO_CLIP,
            n_frames=2,
            rig="webcams",
            width=demo.DEMO_SIZE[0],
            height=demo.DEMO_SIZE[1],
            noise_sigma=0.01,
            seed=0,
        ),
        progress=False,
    )
    _, params, w0, q0 = demo.demo_setup(seq, False)
    state = shirt.init(params, w0, q0)
    frames = jnp.asarray(seq.frames[0])
    return lambda: shirt_sequence._step_jit.lower(params, state, frames, None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("program", choices=["pf", "shirt"])
    ap.add_argument(
        "--default",
        action="store_true",
        help="pf: the plain filter_step, XLA's default compile options",
    )
    ap.add_argument("--top", type=int, default=15, help="source functions listed")
    a = ap.parse_args()
    lower = _pf(a.default) if a.program == "pf" else _shirt()
    t0 = time.perf_counter()
    lowered = lower()
    t1, c1 = time.perf_counter(), time.process_time()
    compiled = lowered.compile()
    t2, c2 = time.perf_counter(), time.process_time()
    inner = getattr(compiled, "compiled", compiled)  # equinox wraps jax's Compiled
    parts = attribute(inner.as_text())
    total_k = sum(k for k, _ in parts.values())
    total_i = sum(i for _, i in parts.values())
    print(
        json.dumps(
            {
                "program": a.program,
                "default": a.default,
                "trace_lower_s": round(t1 - t0, 2),
                "compile_s": round(t2 - t1, 2),
                "compile_cpu_s": round(c2 - c1, 2),
                "kernels": total_k,
                "fused_instructions": total_i,
            }
        )
    )
    for name, (k, i) in list(parts.items())[: a.top]:
        print(f"{k:6d} kernels {i:7d} instructions  {name}")


if __name__ == "__main__":
    main()
