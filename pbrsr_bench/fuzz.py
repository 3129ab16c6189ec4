"""`pbrsr bench fuzz`: mutation fuzzing of the GLB/glTF reader, the writer and zip extraction.

Seeds are valid procedural assets (a GLB quad, the feature-rich test asset as GLB, a glTF with
data URIs, a glTF with external .bin/.png files, and a zip of the latter). Each case applies
1-3 mutations to one seed:

* bytes: bit flips, truncation, inserted/deleted spans, 32-bit fields overwritten with
  boundary values (GLB header and chunk lengths: "chunk-length lies"), a mutated sidecar file;
* JSON (the document is re-serialised and, for a GLB, repacked with honest lengths so the
  mutation reaches the reader's deeper checks): a value replaced by a wrong type, a huge or
  negative number, NaN/Inf, an out-of-range index, a deleted key or array element, a copied
  subtree, a traversal URI;
* zip: entry names with ``../``, absolute paths, backslashes, symlink entries, duplicate
  entries, two models, a dropped resource, followed by optional byte mutations.

A case then goes through ``detect_kind`` -> ``extract_zip`` -> ``load_asset`` and, when that
succeeds, ``save_asset`` (GLB and glTF) and a reload. The only acceptable outcomes are success
or a :class:`~pbrsr_core.errors.PbrsrError`; anything else is an *escape*: its reproducer (the
case's files and a JSON with the traceback) is saved under ``<out>/findings/``. Files written
outside the case's own folder are escapes too.

Mutations draw their choices through a small :class:`Draw` interface, so the same mutators run
from a seeded numpy generator here (case ``i`` of seed ``s`` is reproducible) and from
hypothesis' ``st.data()`` in ``tests/core/asset/test_fuzz.py`` (with shrinking).
"""

from __future__ import annotations

import io
import json
import math
import shutil
import struct
import tempfile
import time
import traceback
import warnings
import zipfile
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from pbrsr_core.asset import detect_kind, extract_zip, load_asset, make_quad_asset, make_test_asset
from pbrsr_core.asset.gltf_read import CHUNK_BIN, CHUNK_JSON, parse_glb
from pbrsr_core.asset.gltf_write import save_asset
from pbrsr_core.errors import PbrsrError
from pbrsr_core.limits import Limits

from .results import pyplot, write_result
from .shared import SHARED_ASSETS

# small limits keep every case fast (a mutated size field cannot ask for gigabytes)
FUZZ_LIMITS = Limits(
    max_file_bytes=16 * 1024 * 1024,
    max_triangles=200_000,
    max_texture_dim=2048,
    max_output_dim=4096,
    max_data_uri_bytes=4 * 1024 * 1024,
    max_zip_entries=64,
    max_unpacked_bytes=64 * 1024 * 1024,
)

INTERESTING: tuple[Any, ...] = (
    0,
    1,
    -1,
    2,
    3,
    4,
    7,
    255,
    65535,
    2**31 - 1,
    2**31,
    2**32 - 1,
    2**53 + 1,
    10**30,
    -(10**30),
    1e308,
    -0.5,
    0.5,
    math.nan,
    math.inf,
    -math.inf,
    "",
    "x",
    "../x.bin",
    "/etc/passwd",
    "file:///etc/passwd",
    "http://example.com/a.bin",
    "data:,",
    "data:application/octet-stream;base64,AAAA",
    "data:image/png;base64,!!!",
    "%2e%2e/%2e%2e/x",
    "C:\\x.bin",
    "a\x00b",
    [],
    {},
    None,
    True,
    False,
    [1, 2, 3],
    [0.0] * 16,
    {"a": 1},
    "a" * 5000,
)
INT_FIELDS: tuple[int, ...] = (0, 1, 3, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFF, 0xFFFFFFF0, 20, 12)


class Draw(Protocol):
    """Source of a case's choices: ``int(lo, hi)`` inclusive."""

    def int(self, lo: int, hi: int) -> int: ...


class RngDraw:
    """Draw from a numpy generator (the bench)."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def int(self, lo: int, hi: int) -> int:
        return int(self.rng.integers(lo, hi + 1)) if hi > lo else lo


def choice(draw: Draw, seq):
    return seq[draw.int(0, len(seq) - 1)]


@dataclass
class Seed:
    """A valid asset: ``name`` of the main file, its bytes, and sidecar files by name."""

    label: str
    name: str
    data: bytes
    resources: dict[str, bytes] = field(default_factory=dict)


@dataclass
class Case:
    seed: str
    name: str
    data: bytes
    resources: dict[str, bytes]
    ops: list[str]


# ----------------------------------------------------------------------------- seeds
def make_seeds(folder: Path, shared: bool = False) -> list[Seed]:
    """The valid procedural assets mutations start from (plus the GLB files of
    the shared assets folder under 2 MB when ``shared`` and the folder exists)."""
    folder = Path(folder)
    seeds = []
    p = make_quad_asset(folder / "quad" / "quad.glb", size=8, subdiv=2)
    seeds.append(Seed("quad.glb", "a.glb", p.read_bytes()))
    p = make_test_asset(folder / "rich" / "rich.glb", size=8)
    seeds.append(Seed("rich.glb", "a.glb", p.read_bytes()))
    p = make_test_asset(
        folder / "datauri" / "d.gltf", size=8, features={"data_uri", "png16", "texcoord1"}
    )
    seeds.append(Seed("datauri.gltf", "a.gltf", p.read_bytes()))
    p = make_quad_asset(folder / "ext" / "quad.gltf", size=8, subdiv=2)
    res = {f.name: f.read_bytes() for f in p.parent.iterdir() if f.name != p.name}
    seeds.append(Seed("external.gltf", "quad.gltf", p.read_bytes(), res))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        zf.writestr("model/quad.gltf", p.read_bytes())
        for k, v in res.items():
            zf.writestr(f"model/{k}", v)
    seeds.append(Seed("external.zip", "a.zip", buf.getvalue()))
    if shared and SHARED_ASSETS.is_dir():
        for g in sorted(SHARED_ASSETS.rglob("*.glb")):
            if g.stat().st_size < 2 * 1024 * 1024:
                seeds.append(Seed(f"shared:{g.name}", "a.glb", g.read_bytes()))
    return seeds


# ----------------------------------------------------------------------------- byte mutations
def mutate_bytes(data: bytes, draw: Draw) -> tuple[bytes, str]:
    """One byte-level mutation of ``data``; returns (new bytes, description)."""
    b = bytearray(data)
    n = len(b)
    op = draw.int(0, 5)
    if n == 0:
        return bytes(draw.int(0, 255) for _ in range(draw.int(1, 16))), "fill"
    if op == 0:
        k = draw.int(1, 8)
        for _ in range(k):
            i = draw.int(0, n - 1)
            b[i] ^= 1 << draw.int(0, 7)
        return bytes(b), f"flip{k}"
    if op == 1:
        cut = draw.int(0, n - 1)
        return bytes(b[:cut]), f"truncate@{cut}"
    if op == 2:
        i = draw.int(0, n - 1)
        ln = draw.int(1, 64)
        return bytes(b[:i] + b[i + ln :]), f"delete@{i}+{ln}"
    if op == 3:
        i = draw.int(0, n)
        ln = draw.int(1, 64)
        junk = bytes(draw.int(0, 255) for _ in range(ln))
        return bytes(b[:i]) + junk + bytes(b[i:]), f"insert@{i}+{ln}"
    # a 32-bit little-endian field set to a boundary value: GLB header/chunk lengths first
    if data[:4] == b"glTF" and n >= 20:
        jlen = struct.unpack_from("<I", data, 12)[0]
        fields = [8, 12, 16, 20 + jlen, 24 + jlen, 4]
        off = choice(draw, [f for f in fields if f + 4 <= n] or [0])
    else:
        off = draw.int(0, max(0, n - 4)) // 4 * 4 if op == 4 else draw.int(0, max(0, n - 4))
    if off + 4 > n:
        return bytes(b[:off]), f"truncate@{off}"
    val = choice(draw, INT_FIELDS + (n, n + 4, n - 8, draw.int(0, 2**32 - 1)))
    struct.pack_into("<I", b, off, val % 2**32)
    return bytes(b), f"u32@{off}={val % 2**32}"


# ----------------------------------------------------------------------------- JSON mutations
def _slots(doc) -> list[tuple[Any, Any]]:
    """Every (container, key) of the document tree (dict keys and list indices)."""
    out, stack = [], [doc]
    while stack and len(out) < 20000:
        o = stack.pop()
        if isinstance(o, dict):
            for k, v in o.items():
                out.append((o, k))
                stack.append(v)
        elif isinstance(o, list):
            for i, v in enumerate(o):
                out.append((o, i))
                stack.append(v)
    return out


def _copy(v):
    return json.loads(json.dumps(v, allow_nan=True))


def mutate_json(doc: dict, draw: Draw) -> str:
    """One in-place mutation of a glTF document; returns a description."""
    slots = _slots(doc)
    if not slots:
        doc["asset"] = choice(draw, INTERESTING)
        return "asset"
    holder, key = choice(draw, slots)
    old = holder[key]
    op = draw.int(0, 6)
    if op <= 1:  # wrong type / boundary value
        holder[key] = _copy(choice(draw, INTERESTING))
        return f"set {key!r}"
    if op == 2 and isinstance(old, (int, float)) and not isinstance(old, bool):
        # nearby or out-of-range number (indices, counts, offsets)
        delta = choice(draw, (1, -1, 2, 1000, -1000, 2**20, -(2**31)))
        holder[key] = (old + delta) if isinstance(old, int) else old * choice(draw, (-1, 1e9, 0))
        return f"shift {key!r}"
    if op == 3:  # delete a key or an element
        del holder[key]
        return f"delete {key!r}"
    if op == 4 and isinstance(holder, list):  # duplicate an element
        holder.insert(key, _copy(old))
        return f"dup {key!r}"
    if op == 5:  # a copy of another subtree in its place
        other_holder, other_key = choice(draw, slots)
        holder[key] = _copy(other_holder[other_key])
        return f"graft {key!r}<-{other_key!r}"
    if isinstance(holder, dict):  # an unknown sibling key or a required one removed
        holder[choice(draw, ("extras", "extensions", "uri", "bufferView", "sparse", "x"))] = _copy(
            choice(draw, INTERESTING)
        )
        return f"add@{key!r}"
    holder.append(_copy(choice(draw, INTERESTING)))
    return "append"


def pack_glb(doc: dict, bin_chunk: bytes | None) -> bytes:
    js = json.dumps(doc, allow_nan=True).encode("utf-8")
    js += b" " * (-len(js) % 4)
    body = struct.pack("<II", len(js), CHUNK_JSON) + js
    if bin_chunk is not None:
        body += struct.pack("<II", len(bin_chunk), CHUNK_BIN) + bin_chunk
    return struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body


# ----------------------------------------------------------------------------- zip mutations
def _zip_with(entries: list[tuple[zipfile.ZipInfo, bytes]]) -> bytes:
    buf = io.BytesIO()
    with warnings.catch_warnings(), zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        warnings.simplefilter("ignore")  # duplicate names are the point
        for info, data in entries:
            zf.writestr(info, data)
    return buf.getvalue()


def mutate_zip(data: bytes, draw: Draw) -> tuple[bytes, str]:
    """One structural mutation of a valid zip (names, symlinks, duplicates, extra models)."""
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        entries = [(info, zf.read(info)) for info in zf.infolist()]
    op = draw.int(0, 6)
    i = draw.int(0, len(entries) - 1)
    info, body = entries[i]
    new = zipfile.ZipInfo(info.filename)
    new.compress_type = zipfile.ZIP_DEFLATED
    if op == 0:
        new.filename = choice(
            draw,
            (
                "../" + info.filename,
                "/abs/" + info.filename,
                "a\\..\\..\\" + info.filename,
                "C:/" + info.filename,
                "model/../../" + info.filename,
                "",
                "./",
            ),
        )
        entries[i] = (new, body)
        return _zip_with(entries), f"name {new.filename!r}"
    if op == 1:  # a symlink entry
        new.create_system = 3
        new.external_attr = (0o120777 << 16) | 0
        entries[i] = (new, b"/etc/passwd")
        return _zip_with(entries), f"symlink {info.filename}"
    if op == 2:  # the same name twice
        entries.append((new, body))
        return _zip_with(entries), f"dup {info.filename}"
    if op == 3:  # a second model
        extra = zipfile.ZipInfo("other.glb")
        entries.append((extra, b"glTF" + bytes(16)))
        return _zip_with(entries), "second model"
    if op == 4 and len(entries) > 1:  # a resource dropped
        entries.pop(i)
        return _zip_with(entries), f"drop {info.filename}"
    if op == 5:  # a directory and a file under it with the same name
        d = zipfile.ZipInfo(info.filename + "/")
        entries.append((d, b""))
        return _zip_with(entries), f"dir {info.filename}/"
    out, desc = mutate_bytes(data, draw)
    return out, desc


# ----------------------------------------------------------------------------- a case
def make_case(seed: Seed, draw: Draw) -> Case:
    """1-3 mutations of ``seed`` chosen by ``draw``."""
    data, res = seed.data, dict(seed.resources)
    ops: list[str] = []
    is_zip = data[:2] == b"PK"
    is_glb = data[:4] == b"glTF"
    for _ in range(draw.int(1, 3)):
        layer = draw.int(0, 9)
        if is_zip:
            if layer < 6:
                try:
                    data, d = mutate_zip(data, draw)
                except Exception:  # noqa: BLE001 - the mutator meets an already broken zip
                    data, d = mutate_bytes(data, draw)
            else:
                data, d = mutate_bytes(data, draw)
            ops.append(f"zip:{d}")
        elif layer < 6:  # JSON
            try:
                if is_glb:
                    doc, bin_chunk = parse_glb(data)
                    ops.append(f"json:{mutate_json(doc, draw)}")
                    data = pack_glb(doc, bin_chunk)
                else:
                    doc = json.loads(data.decode("utf-8-sig"))
                    ops.append(f"json:{mutate_json(doc, draw)}")
                    data = json.dumps(doc, allow_nan=True).encode("utf-8")
            except (PbrsrError, ValueError, UnicodeDecodeError, RecursionError):
                data, d = mutate_bytes(data, draw)
                ops.append(f"bytes:{d}")
        elif layer < 8 or not res:
            data, d = mutate_bytes(data, draw)
            ops.append(f"bytes:{d}")
        else:  # a sidecar file (.bin / .png)
            k = choice(draw, sorted(res))
            res[k], d = mutate_bytes(res[k], draw)
            ops.append(f"{k}:{d}")
    return Case(seed.label, seed.name, data, res, ops)


def run_case(case: Case, work: Path, limits: Limits = FUZZ_LIMITS, load=load_asset) -> str:
    """Load (and on success save and reload) one case inside ``work`` (emptied first).

    Returns the outcome: "ok", "ok-saved" or the PbrsrError class name. Any other exception
    propagates: that is an escape.
    """
    if work.exists():
        shutil.rmtree(work)
    inp = work / "in"
    inp.mkdir(parents=True)
    main = inp / case.name
    main.write_bytes(case.data)
    for k, v in case.resources.items():
        (inp / k).write_bytes(v)
    try:
        kind = detect_kind(main)
        path = extract_zip(main, work / "unzipped", limits) if kind == "zip" else main
        asset = load(path, limits)
        for suffix in ("glb", "gltf"):
            out = work / f"out_{suffix}" / f"r.{suffix}"
            save_asset(asset, out)
            again = load_asset(out, limits, unwrap_missing_uvs=False)
            if again.mesh.num_triangles != asset.mesh.num_triangles:
                raise AssertionError("the saved asset lost triangles")
        return "ok-saved"
    except PbrsrError as exc:
        return type(exc).__name__


def _outside_writes(root: Path, allowed: set[str]) -> list[str]:
    return sorted(p.name for p in root.iterdir() if p.name not in allowed)


def _save_finding(out_dir: Path, index: int, case: Case, exc: BaseException) -> Path:
    d = out_dir / "findings" / f"{index:06d}-{type(exc).__name__}"
    d.mkdir(parents=True, exist_ok=True)
    (d / case.name).write_bytes(case.data)
    for k, v in case.resources.items():
        (d / k).write_bytes(v)
    (d / "finding.json").write_text(
        json.dumps(
            {
                "seed": case.seed,
                "ops": case.ops,
                "error": f"{type(exc).__name__}: {exc}"[:2000],
                "traceback": traceback.format_exception(exc)[-12:],
                "main": case.name,
            },
            indent=2,
        )
    )
    return d


# ----------------------------------------------------------------------------- the benchmark
MEMORY_CAP_MIB = 2048
"""Address-space limit (RLIMIT_AS) of the process that runs the cases."""
CASE_TIMEOUT_S = 60.0
"""A case that runs longer is a finding (the case process is restarted)."""


def _escape(index: int, case: Case, exc: BaseException, out_dir: Path) -> dict:
    return {
        "index": index,
        "seed": case.seed,
        "ops": case.ops,
        "error": f"{type(exc).__name__}: {str(exc)[:300]}",
        "path": str(_save_finding(out_dir, index, case, exc)),
    }


def _case_of(seeds: list[Seed], seed: int, index: int) -> tuple[Seed, Case]:
    s = seeds[index % len(seeds)]
    return s, make_case(s, RngDraw(np.random.default_rng([seed, index])))


def _one(index: int, seed: int, seeds: list[Seed], root: Path, out_dir: Path, load) -> dict:
    """Case ``index``: its outcome, time, and the escape it found (if any)."""
    import resource

    s, case = _case_of(seeds, seed, index)
    t0 = time.perf_counter()
    escape = None
    try:
        outcome = run_case(case, root / "case", load=load)
    except Exception as exc:  # noqa: BLE001 - an escape is what we are looking for
        outcome = f"ESCAPE {type(exc).__name__}"
        escape = _escape(index, case, exc, out_dir)
    stray = _outside_writes(root, {"seeds", "case"})
    if stray:
        outcome = "ESCAPE write-outside"
        exc = RuntimeError(f"files written outside the case folder: {stray}")
        escape = _escape(index, case, exc, out_dir)
        for name in stray:
            shutil.rmtree(root / name, ignore_errors=True)
    return {
        "index": index,
        "seed": s.label,
        "outcome": outcome,
        "seconds": time.perf_counter() - t0,
        "escape": escape,
        "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def _case_process(conn, seed: int, shared: bool, root: Path, out_dir: Path, cap_mib: int, load):
    """The child that runs cases: address space capped, then case indices in, results out."""
    import resource

    if cap_mib:
        cap = cap_mib * 1024 * 1024
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
    seeds = make_seeds(root / "seeds", shared)
    conn.send(len(seeds))
    while (index := conn.recv()) is not None:
        conn.send(_one(index, seed, seeds, root, out_dir, load))


class _CaseRunner:
    """A capped child process that runs one case at a time; restarted after it dies."""

    def __init__(self, seed: int, shared: bool, root: Path, out_dir: Path, cap_mib: int, load):
        import multiprocessing

        self.ctx = multiprocessing.get_context("spawn")
        self.args = (seed, shared, root, out_dir, cap_mib, load)
        self.root = root
        self.proc = None
        self.conn = None

    def _start(self) -> None:
        shutil.rmtree(self.root, ignore_errors=True)
        self.root.mkdir(parents=True)
        self.conn, child = self.ctx.Pipe()
        self.proc = self.ctx.Process(target=_case_process, args=(child, *self.args), daemon=True)
        self.proc.start()
        child.close()
        if not self.conn.poll(300):
            raise RuntimeError("the fuzz case process did not start")
        self.conn.recv()

    def run(self, index: int, timeout: float) -> dict | str:
        """The case's result, or why the process ended without one ("timeout", "exit 1",
        "signal 9")."""
        if self.proc is None or not self.proc.is_alive():
            self._start()
        self.conn.send(index)
        try:
            if self.conn.poll(timeout):
                return self.conn.recv()
            why = f"timeout after {timeout:.0f} s"
        except (EOFError, ConnectionError):
            why = ""
        self.stop(kill=True)
        code = self.proc.exitcode
        return why or (f"signal {-code}" if code is not None and code < 0 else f"exit {code}")

    def stop(self, kill: bool = False) -> None:
        if self.proc is None:
            return
        if kill:
            self.proc.kill()
        elif self.proc.is_alive():
            self.conn.send(None)
        self.proc.join(30)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()


def run(
    *,
    cases: int = 3000,
    seed: int = 0,
    start: int = 0,
    out_dir: Path = Path("bench-out/fuzz"),
    shared: bool = False,
    memory_cap_mib: int = MEMORY_CAP_MIB,
    case_timeout_s: float = CASE_TIMEOUT_S,
    load=load_asset,
    log=None,
) -> dict:
    """Fuzz cases ``start .. start + cases - 1`` of ``seed``; write ``fuzz.json`` and
    ``fuzz.png`` into ``out_dir``.

    The cases run in a child process whose address space is capped at ``memory_cap_mib``
    (RLIMIT_AS; 0: no cap): an asset that makes the reader allocate past it is a finding
    (MemoryError), and a case that kills or hangs the process is one too ("crash: signal 9",
    "crash: timeout"); the process is restarted and the run goes on. ``load`` is the reader
    (a picklable function; the tests pass broken ones).

    Returns {"cases", "start", "seconds", "cases_per_s", "outcomes" {name: n}, "by_seed"
    {seed: {outcome: n}}, "escapes" [{index, seed, ops, error, path}], "slowest" [...],
    "memory_cap_mib", "peak_rss_mib"}.
    """
    out_dir = Path(out_dir).resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    shutil.rmtree(out_dir / "findings", ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix="pbrsr-fuzz-"))
    outcomes: Counter[str] = Counter()
    by_seed: dict[str, Counter[str]] = {}
    escapes: list[dict] = []
    slowest: list[tuple[float, int, str]] = []
    peak = 0.0
    if shared and not SHARED_ASSETS.is_dir() and log:
        log(f"{SHARED_ASSETS} does not exist: procedural seeds only")
    runner = _CaseRunner(seed, shared, tmp / "cases", out_dir, memory_cap_mib, load)
    seeds: list[Seed] = []
    try:
        t0 = time.perf_counter()
        for n, index in enumerate(range(start, start + cases), 1):
            res = runner.run(index, case_timeout_s)
            if isinstance(res, str):  # the process died or hung: regenerate the case here
                seeds = seeds or make_seeds(tmp / "parent-seeds", shared)
                s, case = _case_of(seeds, seed, index)
                exc = RuntimeError(f"the case process ended: {res}")
                escapes.append(_escape(index, case, exc, out_dir))
                res = {"seed": s.label, "outcome": "ESCAPE crash", "seconds": case_timeout_s}
            elif res["escape"]:
                escapes.append(res["escape"])
            if "peak_rss_mib" in res:
                peak = max(peak, res["peak_rss_mib"])
            slowest = sorted([*slowest, (res["seconds"], index, res["seed"])], reverse=True)[:5]
            outcomes[res["outcome"]] += 1
            by_seed.setdefault(res["seed"], Counter())[res["outcome"]] += 1
            if log and n % 500 == 0:
                log(f"{n}/{cases} cases, {len(escapes)} escapes, peak RSS {peak:.0f} MiB")
        seconds = time.perf_counter() - t0
    finally:
        runner.stop()
        shutil.rmtree(tmp, ignore_errors=True)
    result = {
        "cases": cases,
        "seed": seed,
        "start": start,
        "seconds": round(seconds, 3),
        "cases_per_s": round(cases / max(seconds, 1e-9), 1),
        "outcomes": dict(outcomes.most_common()),
        "by_seed": {k: dict(v.most_common()) for k, v in by_seed.items()},
        "escapes": escapes,
        "slowest": [{"seconds": round(t, 3), "index": i, "seed": lbl} for t, i, lbl in slowest],
        "memory_cap_mib": memory_cap_mib,
        "peak_rss_mib": round(peak, 1),
        "shared_assets": SHARED_ASSETS.is_dir() and shared,
    }
    return write_result(result, out_dir, "fuzz", _plot)


def _plot(result: dict, path: Path) -> None:
    plt = pyplot()

    names = list(result["outcomes"])
    counts = [result["outcomes"][n] for n in names]
    fig, ax = plt.subplots(figsize=(8, 0.4 * len(names) + 1.5))
    colours = ["tab:red" if n.startswith("ESCAPE") else "tab:blue" for n in names]
    ax.barh(names, counts, color=colours)
    ax.invert_yaxis()
    ax.set_xlabel("cases")
    ax.set_title(
        f"fuzz: {result['cases']} cases, {result['cases_per_s']} cases/s, "
        f"{len(result['escapes'])} escapes"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def print_table(result: dict) -> None:
    from rich.console import Console
    from rich.table import Table

    console = Console()
    t = Table(title=f"pbrsr bench fuzz (seed {result['seed']})")
    t.add_column("outcome")
    t.add_column("cases", justify="right")
    t.add_column("share", justify="right")
    for name, n in result["outcomes"].items():
        style = "red" if name.startswith("ESCAPE") else None
        t.add_row(name, str(n), f"{100 * n / result['cases']:.1f}%", style=style)
    console.print(t)
    first, last = result["start"], result["start"] + result["cases"] - 1
    cap = f"{result['memory_cap_mib']} MiB" if result["memory_cap_mib"] else "none"
    console.print(
        f"cases {first}..{last} of seed {result['seed']} in {result['seconds']:.1f} s "
        f"({result['cases_per_s']} cases/s); escapes: {len(result['escapes'])}; "
        f"peak RSS of the case process {result['peak_rss_mib']:.0f} MiB (cap {cap})"
    )
    for e in result["escapes"][:10]:
        console.print(f"[red]escape[/red] #{e['index']} {e['seed']} {e['ops']}: {e['error']}")
