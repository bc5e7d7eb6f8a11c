"""Reading an optimised XLA module's text (`compiled.as_text()`): its size, where its instructions
come from, and how many bytes its kernels move.

    hlo_instructions(text) -> int                       instructions, fused computations included
    instruction_sources(text) -> {name: (opcode, source, op_name)}
    hlo_by_source(text) -> {source: instructions}
    kernel_traffic(text) -> ({name: bytes per run}, loops of unknown trip count)
    gb_moved(text) -> float                             their total in GB (NaN if unparsable)

The source of an instruction is the innermost hron_jax module on its stack (`bench compile
--by-source`, `bench profile`); stacks must be deep enough to reach our frames (`deep_tracebacks`).
`kernel_traffic` estimates the DRAM bytes each top-level op (kernel, copy, library call) moves per
run of the module; on a GPU the HGT layers are bound by that traffic, so the estimate ranks changes
to the GPU program on a machine without a GPU (`bench compile --gpu-target`; calibrated against an
H200's profile in docs/benchmarks.md).
"""

from __future__ import annotations

import re

# An instruction line of an HLO module's text: its name and opcode.
_INSTRUCTION = re.compile(r"\s*(?:ROOT )?%(\S+) = .*? ([a-z][\w-]*)\(")


def hlo_instructions(text: str) -> int:
    """Instructions of an optimised HLO module's text, those of fused computations included."""
    return sum(1 for line in text.splitlines() if _INSTRUCTION.match(line))


def instruction_sources(text: str, lines: bool = False) -> dict[str, tuple[str, str, str]]:
    """{instruction name: (opcode, source, op_name)} of an optimised HLO module's text (op_name:
    the JAX name stack of its metadata, e.g. '.../transpose(jvp(ActorCritic))/.../scatter-add').
    The source is the innermost hron_jax file on the instruction's stack (metadata stack frames;
    with `lines`, file:line, e.g. 'models/gnn.py:459'),
    'via' the library whose code emitted it when that is not ours (e.g. 'sim.py via mujoco'),
    '(no hron_jax frame) via LIB' when the stack does not reach our code (e.g. MJX kinematics
    traced inside MJX's own scans, optax; JAX drops its own frames), or "XLA's own" for what
    XLA inserted (copies, layout changes; no metadata). Parameters are left out. Needs stacks
    deep enough to reach our frames: compile with jax_traceback_in_locations_limit raised
    (`deep_tracebacks`)."""
    sections, current = {}, None
    for line in text.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            current = sections.setdefault(line, {})
            continue
        m = re.match(r"(\d+) (.*)", line) if current is not None else None
        if m:
            current[int(m.group(1))] = m.group(2)
        else:
            current = None
    files = {k: v.strip('"') for k, v in sections.get("FileNames", {}).items()}
    loc_file, loc_line = {}, {}
    for k, v in sections.get("FileLocations", {}).items():
        loc_file[k] = files[int(re.search(r"file_name_id=(\d+)", v).group(1))]
        line = re.search(r"\bline=(\d+)", v)
        loc_line[k] = line.group(1) if line else "?"
    frames = {}
    for k, v in sections.get("StackFrames", {}).items():
        loc, parent = (int(x) for x in re.findall(r"=(\d+)", v)[:2])
        frames[k] = (loc, parent)

    def key(frame: int) -> str:
        inner, seen = None, set()
        while frame in frames and frame not in seen:
            seen.add(frame)
            loc, parent = frames[frame]
            path = loc_file[loc]
            if inner is None:
                inner = path
            if "/hron_jax/" in path:
                name = path.split("/hron_jax/", 1)[1] + (f":{loc_line[loc]}" if lines else "")
                if "/hron_jax/" not in inner:
                    lib = inner.split("site-packages/", 1)[-1].split("/", 1)[0]
                    name += f" via {lib}"
                return name
            frame = parent
        if inner is None:
            return "(no hron_jax frame)"
        # e.g. MJX internals traced where the stack no longer reaches our code, optax: name the
        # library whose code emitted it (JAX drops its own frames, so jax.random is never here)
        lib = inner.split("site-packages/", 1)[-1].split("/", 1)[0] if "site-packages/" in inner else inner
        return f"(no hron_jax frame) via {lib.rsplit('/', 1)[-1]}"

    out = {}
    for line in text.splitlines():
        m = _INSTRUCTION.match(line)
        if m and m.group(2) != "parameter":
            frame = re.search(r"stack_frame_id=(\d+)", line)
            op_name = re.search(r'op_name="([^"]*)"', line)
            out[m.group(1)] = (
                m.group(2),
                key(int(frame.group(1))) if frame else "(XLA's own: no source)",
                op_name.group(1) if op_name else "",
            )
    return out


def hlo_by_source(text: str) -> dict[str, int]:
    """Instructions of an optimised HLO module's text per source (`instruction_sources`), most first."""
    counts: dict[str, int] = {}
    for _, source, _ in instruction_sources(text).values():
        counts[source] = counts.get(source, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: -kv[1]))


def deep_tracebacks() -> None:
    """Stacks deep enough to reach hron_jax frames under MJX / flax / optax code (for
    `instruction_sources`). They make bigger modules that compile slower, so only the source
    tables use them, on programs traced afresh."""
    import jax

    jax.config.update("jax_traceback_in_locations_limit", 64)
    jax.clear_caches()


# ---- kernel traffic ----------------------------------------------------------------------------

_ARRAY = re.compile(r"\b(pred|[su](?:4|8|16|32|64)|bf16|f(?:8\w*|16|32|64))\[([\d,]*)\]")
_COMPUTATION = re.compile(r"^(ENTRY )?%([\w.\-]+) .*\{$")
_OP = re.compile(r"^\s*(?:ROOT )?%([\w.\-]+) = (.*?) ([a-z][\w\-]*)\((.*)$")
# ops that launch nothing of their own (control flow: the ops of their bodies count)
_FREE = {
    "parameter",
    "constant",
    "get-tuple-element",
    "tuple",
    "bitcast",
    "while",
    "call",
    "conditional",
    "opt-barrier",
    "after-all",
    "partition-id",
    "replica-id",
}
_WINDOWS = ("gather", "slice", "dynamic-slice")  # ops that read only part of their first operand
# ops whose every result element reads the same element of each operand (of the result's dims)
_ELEMENTWISE = {
    "abs", "add", "and", "atan2", "cbrt", "ceil", "clamp", "compare", "convert", "copy", "cosine",
    "divide", "erf", "exponential", "exponential-minus-one", "floor", "is-finite", "log",
    "log-plus-one", "logistic", "maximum", "minimum", "multiply", "negate", "not", "or", "power",
    "remainder", "round-nearest-afz", "round-nearest-even", "rsqrt", "select", "sign", "sine",
    "sqrt", "subtract", "tan", "tanh", "xor",
}  # fmt: skip


def _bytes(shape: str) -> int:
    """Bytes of an HLO shape (an array or a tuple of arrays; layouts ignored)."""
    total = 0
    for dtype, dims in _ARRAY.findall(shape):
        n = 1
        for d in filter(None, dims.split(",")):
            n *= int(d)
        bits = 1 if dtype == "pred" else 8 if dtype.startswith("f8") else int(re.sub(r"\D", "", dtype))
        total += n * max(bits, 8) // 8
    return total


def _parameters(body: list[dict]) -> dict[str, int]:
    """{parameter name: its index} of a computation."""
    out = {}
    for op in body:
        index = re.match(r"\s*(\d+)", op["args"]) if op["opcode"] == "parameter" else None
        if index:
            out[op["name"]] = int(index.group(1))
    return out


def _parse(text: str) -> tuple[dict[str, list[dict]], str | None]:
    """{computation: [op: name, shape, opcode, operands, attrs]} and the entry computation's name."""
    comps, current, entry = {}, None, None
    for line in text.splitlines():
        m = _COMPUTATION.match(line)
        if m:
            current = comps.setdefault(m.group(2), [])
            entry = m.group(2) if m.group(1) else entry
            continue
        m = _OP.match(line)
        if m is None or current is None:
            continue
        name, shape, opcode, rest = m.groups()
        depth, end = 1, 0
        while end < len(rest) and depth:  # the operand list ends at its closing parenthesis
            depth += {"(": 1, ")": -1}.get(rest[end], 0)
            end += 1
        args = rest[: end - 1]
        operands = re.findall(r"%([\w.\-]+)", args)
        attrs = rest[end:]
        current.append(dict(name=name, shape=shape, opcode=opcode, args=args, operands=operands, attrs=attrs))
    return comps, entry


def _callees(op: dict) -> list[tuple[str, int]]:
    """(computation, runs per run of op) of a control-flow op: a while's body and condition run its
    known trip count (once when XLA does not know it: a lower bound), a call's and each conditional
    branch once."""
    a = op["attrs"]
    if op["opcode"] == "while":
        trips = re.search(r'"known_trip_count":\{"n":"(\d+)"', a)
        n = int(trips.group(1)) if trips else 1
        return [(c, n) for c in re.findall(r"(?:body|condition)=%([\w.\-]+)", a)]
    if op["opcode"] == "call":
        return [(c, 1) for c in re.findall(r"to_apply=%([\w.\-]+)", a)]
    if op["opcode"] == "conditional":
        branches = re.search(r"branch_computations=\{([^}]*)\}", a)
        names = re.findall(r"%([\w.\-]+)", branches.group(1)) if branches else []
        return [(c, 1) for c in names + re.findall(r"(?:true|false)_computation=%([\w.\-]+)", a)]
    return []


def _fusion_reads(body: list[dict], reads: list[int]) -> list[int]:
    """Bytes a fusion reads of each operand: one that reaches only gathers / slices / dynamic slices
    (directly or through bitcasts, concatenations and elementwise ops) is read as much as they
    yield, e.g. the rows that edges gather of a node table, or one type's rows of an elementwise
    function of whole tables."""
    local = {op["name"]: _bytes(op["shape"]) for op in body}
    dims = {op["name"]: [d for _, d in _ARRAY.findall(op["shape"])] for op in body}
    users: dict[str, list[tuple[dict, int]]] = {}
    for op in body:
        for pos, name in enumerate(op["operands"]):
            users.setdefault(name, []).append((op, pos))
    memo: dict[str, float] = {}

    def read(name: str) -> float:
        if name not in memo:
            total = 0.0
            for op, pos in users.get(name, [(None, 0)]):
                if op is None:  # the fusion's result: all of it
                    total = local[name]
                    break
                if op["opcode"] in _WINDOWS and pos == 0:
                    total += local[op["name"]]
                elif op["opcode"] == "bitcast":
                    total += read(op["name"])
                elif op["opcode"] == "concatenate" or (
                    op["opcode"] in _ELEMENTWISE and dims[op["name"]] == dims[name]
                ):  # the share of the result that is read, of this operand
                    total += read(op["name"]) * local[name] / max(local[op["name"]], 1)
                else:
                    total = local[name]
                    break
            memo[name] = min(total, local[name])
        return memo[name]

    out = list(reads)
    for name, k in _parameters(body).items():
        if k < len(out):
            out[k] = min(out[k], int(read(name)))
    return out


def _in_place(op: dict, body: list[dict] | None, shapes: dict[str, str]) -> tuple[int, int] | None:
    """(index of the operand updated in place, bytes written) of a scatter, a dynamic-update-slice
    or a fusion (`body`) around one of them; None for other ops. A scatter reads and writes the rows
    its updates touch: 2x its updates, at most 2x the buffer (updates that meet on one row, as the
    edges of a graph on its nodes' rows, add up in the cache); a dynamic-update-slice writes its
    update."""
    updates = ("scatter", "dynamic-update-slice")
    if op["opcode"] in updates:
        update, local, target = op, shapes, 0
        buffer = _bytes(shapes.get(op["operands"][0], "")) if op["operands"] else 0
    else:
        update = next((o for o in body or [] if o["opcode"] in updates), None)
        if update is None:
            return None
        local = {o["name"]: o["shape"] for o in body}
        index = _parameters(body)
        name = update["operands"][0] if update["operands"] else None
        if name not in index:  # the updated buffer reaches the op through a bitcast or so
            name = next((o for o in index if _bytes(local[o]) == _bytes(op["shape"])), name)
        target, buffer = index.get(name, 0), _bytes(op["shape"])
    if len(update["operands"]) < 2:
        return None
    if update["opcode"] == "dynamic-update-slice":
        return target, _bytes(local.get(update["operands"][1], ""))
    return target, 2 * min(_bytes(local.get(update["operands"][-1], "")), buffer)


def kernel_traffic(text: str) -> tuple[dict[str, int], int]:
    """Estimated DRAM bytes per run of an optimised module, per top-level op, and the number of
    while loops whose trip count XLA does not know (their bodies are counted once).

    Every op of a computation that runs as kernels (the entry, while bodies and conditions, called
    computations, conditional branches: both branches count, an upper bound) moves its result and
    its operands once, times the runs of its computation (while trip counts multiply). Exceptions:
    an operand that a fusion only gathers or slices (also through bitcasts, concatenations and
    elementwise ops) counts what is read of it; an in-place update (a scatter or a
    dynamic-update-slice, or a fusion around one) does not stream the buffer it updates: it reads
    its other operands and the rows it touches, and writes those rows. Caches are otherwise
    ignored, so this estimates memory-bound work: for the HGT layers of the exploratory chunk
    (4096 envs x 16 steps, 8 minibatches) it gave 7.0 TB per update, which one H200 moved in
    1.92 s (3.65 TB/s of its 4.8; docs/benchmarks.md), while compute-bound kernels (convolutions,
    the ray caster) take longer than their bytes say."""
    comps, entry = _parse(text)
    fused = {
        c
        for body in comps.values()
        for op in body
        if op["opcode"] == "fusion"
        for c in re.findall(r"calls=%([\w.\-]+)", op["attrs"])
    }
    runs, unknown = {entry: 1}, 0
    for name in reversed(list(comps)):  # a computation's text comes after those it calls
        if not runs.get(name) or name in fused:
            continue
        for op in comps[name]:
            unknown += op["opcode"] == "while" and "known_trip_count" not in op["attrs"]
            for callee, n in _callees(op):
                runs[callee] = runs.get(callee, 0) + runs[name] * n
    shapes = {op["name"]: op["shape"] for body in comps.values() for op in body}
    out = {}
    for name, body in comps.items():
        if not runs.get(name) or name in fused:
            continue
        for op in body:
            if op["opcode"] in _FREE or op["opcode"].endswith("-done"):
                continue
            written = _bytes(op["shape"])
            reads = [_bytes(shapes.get(o, "")) for o in op["operands"]]
            callee = re.search(r"calls=%([\w.\-]+)", op["attrs"]) if op["opcode"] == "fusion" else None
            fused_body = comps.get(callee.group(1), []) if callee else None
            if fused_body is not None:
                reads = _fusion_reads(fused_body, reads)
            update = _in_place(op, fused_body, shapes) if reads else None
            if update is not None and update[0] < len(reads):
                reads[update[0]], written = 0, update[1]
            elif op["opcode"] in _WINDOWS and reads:
                reads[0] = min(reads[0], written)
            out[op["name"]] = (written + sum(reads)) * runs[name]
    return out, unknown


def gb_moved(text: str) -> float:
    """`kernel_traffic`'s total in GB, NaN where a module's text defeats the parser (another XLA's
    format): an estimate printed beside measurements must never stop them."""
    try:
        return sum(kernel_traffic(text)[0].values()) / 1e9
    except Exception:
        return float("nan")
