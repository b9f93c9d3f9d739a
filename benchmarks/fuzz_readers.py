"""Fuzz the marker-file readers: mutate real files, read them in an isolated worker, classify outcomes.

Every case must end as either a loaded ``Trajectories`` or a ``MocaptkError`` with a one-line message
naming the file. Anything else is a finding: another exception type (a bug), a crash of the worker
process (signal / abort: the interpreter died), or a hang (no answer within the time bound).

Seeds are real files from ``../shared/data`` (C3D, Vicon CSV, TRC, generic CSV) plus files our own
writers produce from the bundled sample. Mutations: byte flips, truncations, parameter-section
corruption, huge counts, NaN/Inf values, wrong units, duplicate labels, non-UTF-8 labels.

Usage::

    python benchmarks/fuzz_readers.py --cases 10000 --seed 1      # per format; writes a summary
"""

from __future__ import annotations

import argparse
import json
import os
import random
import subprocess
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("MOCAPTK_SHARED_DATA", REPO.parent / "shared" / "data"))
FORMATS = ("c3d", "vicon_csv", "trc", "generic_csv")
MAX_SEED_BYTES = 20_000  # text seeds are cut to whole lines: big files add no new structure
MAX_C3D_SEED_BYTES = 1_000_000  # bigger C3D seeds only slow the campaign (same structures)

#: The worker reads one case path per stdin line and answers one JSON line per case.
WORKER = r"""
import json, resource, sys, warnings
warnings.simplefilter("error", RuntimeWarning)  # as in the test suite: a warning is a finding
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
from mocaptk.acquisition.formats import read_trajectories
from mocaptk.errors import MocaptkError
print(json.dumps({"ready": True}), flush=True)
for line in sys.stdin:
    path, rate = line.rstrip("\n").rsplit("\t", 1)
    try:
        t = read_trajectories(path, rate=float(rate) if rate else None)
        out = {"outcome": "loaded", "shape": list(t.positions.shape)}
    except MocaptkError as exc:
        msg = str(exc)
        out = {"outcome": "error", "message": msg,
               "one_line": "\n" not in msg and 0 < len(msg) <= 500, "names_file": path in msg}
    except MemoryError:
        out = {"outcome": "memory", "message": "MemoryError"}
    except Exception as exc:  # a finding: readers must raise MocaptkError
        out = {"outcome": "exception", "message": f"{type(exc).__name__}: {exc}"[:300]}
    print(json.dumps(out), flush=True)
"""


SAMPLE = REPO / "sample_c3d" / "dense_halfface.c3d"


def seed_files(writer_dir: Path | None = None) -> dict[str, list[Path]]:
    """Seed files per format (small real files; missing folders are skipped).

    With ``writer_dir``, our own writers' output of the bundled sample (120 frames across a take
    boundary) is added: the Vicon CSV Events section and the C3D MOCAPTK group get fuzzed too.
    """
    pools = {
        "c3d": sorted(p for p in (SHARED / "c3d").rglob("*")
                      if p.suffix.lower() == ".c3d" and p.stat().st_size <= MAX_C3D_SEED_BYTES),
        "vicon_csv": sorted((SHARED / "csv_trc" / "pyomeca").glob("markers*.csv")),
        "trc": sorted((SHARED / "csv_trc").rglob("*.trc")),
        "generic_csv": sorted((SHARED / "facial_mocap" / "blenderface").glob("Subject_*.csv")),
    }
    if writer_dir is not None and SAMPLE.exists():
        from mocaptk.acquisition.formats import read_trajectories, write_trajectories

        sample = read_trajectories(SAMPLE)
        cut = sample.takes[1].start if len(sample.takes) > 1 else 60
        short = sample.frames(max(0, cut - 60), cut + 60)  # across a take boundary
        pools["c3d"].append(SAMPLE)
        for fmt, ext in (("c3d", ".c3d"), ("vicon_csv", ".csv"), ("trc", ".trc")):
            pools[fmt].append(write_trajectories(short, writer_dir / f"writer_seed{ext}"))
    return {fmt: [p for p in paths if 0 < p.stat().st_size] for fmt, paths in pools.items()}


def seed_name(path: Path) -> str:
    """A seed's name relative to the shared data or the repository (writer seeds: file name)."""
    for root in (SHARED, REPO):
        if path.is_relative_to(root):
            return str(path.relative_to(root))
    return path.name


def load_seed(path: Path) -> bytes:
    """Seed bytes; text files are cut to whole lines below MAX_SEED_BYTES."""
    data = path.read_bytes()
    if len(data) <= MAX_SEED_BYTES or path.suffix.lower() == ".c3d":
        return data
    cut = data.rfind(b"\n", 0, MAX_SEED_BYTES)
    return data[: cut + 1]


# -- mutations -----------------------------------------------------------------------------------
def _flip_bytes(data: bytes, rng: random.Random) -> bytes:
    buf = bytearray(data)
    for _ in range(rng.randint(1, 16)):
        buf[rng.randrange(len(buf))] = rng.randrange(256)
    return bytes(buf)


def _truncate(data: bytes, rng: random.Random) -> bytes:
    return data[: rng.randrange(len(data))]


def _c3d_parameter_corruption(data: bytes, rng: random.Random) -> bytes:
    buf = bytearray(data)
    start = 512 * max(0, buf[0] - 1) if buf else 0
    end = min(len(buf), start + 512 * max(1, buf[start + 2] if len(buf) > start + 2 else 1))
    for _ in range(rng.randint(1, 8)):
        if end > start:
            buf[rng.randrange(start, end)] = rng.randrange(256)
    return bytes(buf)


def _c3d_huge_counts(data: bytes, rng: random.Random) -> bytes:
    buf = bytearray(data)
    # header words: 2 = points, 4/5 = first/last frame, 9 = data start block (1-based words)
    for word in rng.sample([2, 3, 4, 5, 9, 10], rng.randint(1, 3)):
        pos = 2 * (word - 1)
        if pos + 2 <= len(buf):
            buf[pos:pos + 2] = rng.choice([b"\xff\xff", b"\xff\x7f", b"\x00\x00", b"\x00\x80"])
    return bytes(buf)


def _text_lines(data: bytes) -> list[bytes]:
    return data.split(b"\n")


def _text_huge_counts(data: bytes, rng: random.Random) -> bytes:
    lines = _text_lines(data)
    head = min(len(lines), 6)
    i = rng.randrange(head)
    lines[i] = lines[i].replace(b"\t", b"\t999999999\t", 1) if b"\t" in lines[i] else \
        b"1000000000," + lines[i]
    return b"\n".join(lines)


def _text_nan_inf(data: bytes, rng: random.Random) -> bytes:
    lines = _text_lines(data)
    for _ in range(rng.randint(1, 20)):
        i = rng.randrange(len(lines))
        sep = b"\t" if b"\t" in lines[i] else b","
        cells = lines[i].split(sep)
        if cells:
            cells[rng.randrange(len(cells))] = rng.choice([b"nan", b"inf", b"-inf", b"1e400", b"NaN"])
        lines[i] = sep.join(cells)
    return b"\n".join(lines)


def _text_wrong_units(data: bytes, rng: random.Random) -> bytes:
    out = data
    for unit in (b"mm", b"Units\tmm", b"m\t", b"cm"):
        out = out.replace(unit, rng.choice([b"furlong", b"", b"\xff\xfe", b"mmm"]), 1)
    return out


def _text_duplicate_labels(data: bytes, rng: random.Random) -> bytes:
    lines = _text_lines(data)
    for i, line in enumerate(lines[:8]):
        sep = b"\t" if line.count(b"\t") > line.count(b",") else b","
        cells = line.split(sep)
        named = [j for j, c in enumerate(cells) if c.strip() and not c.strip()[:1].isdigit()]
        if len(named) >= 2:
            a, b = rng.sample(named, 2)
            cells[b] = cells[a]
            lines[i] = sep.join(cells)
            break
    return b"\n".join(lines)


def _text_non_utf8(data: bytes, rng: random.Random) -> bytes:
    lines = _text_lines(data)
    i = rng.randrange(min(len(lines), 6))
    pos = rng.randrange(len(lines[i]) + 1)
    lines[i] = lines[i][:pos] + rng.choice([b"\xff", b"\xc3\x28", b"\xed\xa0\x80", b"\x00"]) + lines[i][pos:]
    return b"\n".join(lines)


def _c3d_huge_params(data: bytes, rng: random.Random) -> bytes:
    # overwrite random 16-bit words of the parameter section with extreme values
    buf = bytearray(data)
    start = 512 * max(0, buf[0] - 1) if buf else 0
    for _ in range(rng.randint(1, 6)):
        pos = rng.randrange(start, max(start + 1, min(len(buf) - 2, start + 4096)))
        buf[pos:pos + 2] = rng.choice([b"\xff\xff", b"\xff\x7f", b"\x00\x80"])
    return bytes(buf)


def _text_huge_numbers(data: bytes, rng: random.Random) -> bytes:
    # a frame number, time, rate or coordinate far out of range (10^9 frames, 1e308 mm...)
    lines = _text_lines(data)
    for _ in range(rng.randint(1, 3)):
        i = rng.randrange(len(lines))
        sep = b"\t" if b"\t" in lines[i] else (b";" if b";" in lines[i] else b",")
        cells = lines[i].split(sep)
        numeric = [j for j, c in enumerate(cells) if c.strip()[:1].isdigit() or c.strip()[:1] == b"-"]
        if numeric:
            j = rng.choice(numeric[:2] if rng.random() < 0.5 else numeric)
            cells[j] = rng.choice([b"1000000000", b"999999999999", b"-1000000000", b"1e308",
                                   b"9223372036854775808", b"0", b"-0", b"1e-320"])
            lines[i] = sep.join(cells)
    return b"\n".join(lines)


MUTATIONS = {
    "c3d": [_flip_bytes, _truncate, _c3d_parameter_corruption, _c3d_huge_counts, _c3d_huge_params],
    "text": [_flip_bytes, _truncate, _text_huge_counts, _text_huge_numbers, _text_nan_inf,
             _text_wrong_units, _text_duplicate_labels, _text_non_utf8],
}


def mutate(data: bytes, fmt: str, rng: random.Random) -> tuple[str, bytes]:
    """One random mutation of ``data`` (a seed of format ``fmt``); returns (mutation name, bytes)."""
    pool = MUTATIONS["c3d" if fmt == "c3d" else "text"]
    op = rng.choice(pool)
    return op.__name__.lstrip("_"), op(data, rng) if data else data


# -- running ----------------------------------------------------------------------------------------
@dataclass
class Campaign:
    cases: int = 0
    outcomes: Counter = field(default_factory=Counter)
    findings: list[dict] = field(default_factory=list)
    mutations: Counter = field(default_factory=Counter)
    seconds: float = 0.0


class Worker:
    """A worker subprocess (``script``: reads one request per stdin line, answers one JSON line)
    with a memory limit; restarted after a crash or a hang."""

    script = WORKER

    def __init__(self, memory_limit: int) -> None:
        self.memory_limit = memory_limit
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-c", self.script, str(self.memory_limit)], stdin=subprocess.PIPE,
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, bufsize=1)
        assert json.loads(self.proc.stdout.readline())["ready"]

    def read(self, path: str, timeout: float, rate: float | None = None) -> dict:
        return self.ask(f"{path}\t{rate or ''}", timeout)

    def ask(self, request: str, timeout: float) -> dict:
        """Send one request line; its answer, or ``hang`` / ``crash`` (the worker restarts)."""
        if self.proc is None or self.proc.poll() is not None:
            self.start()
        assert self.proc and self.proc.stdin and self.proc.stdout
        self.proc.stdin.write(request + "\n")
        self.proc.stdin.flush()
        import selectors

        sel = selectors.DefaultSelector()
        sel.register(self.proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout):
            self.proc.kill()
            self.proc.wait()
            self.proc = None
            return {"outcome": "hang"}
        line = self.proc.stdout.readline()
        if not line:
            code = self.proc.wait()
            self.proc = None
            return {"outcome": "crash", "message": f"worker exited with {code}"}
        return json.loads(line)

    def close(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.stdin.close()
            try:
                self.proc.wait(timeout=60)  # a loaded machine: an interpreter's exit can take a while
            except subprocess.TimeoutExpired:  # it stopped the campaign's summary once
                self.proc.kill()
                self.proc.wait()


def make_case(fmt: str, blobs: list[tuple[Path, bytes]], seed: int, i: int) -> tuple[Path, str, bytes]:
    """Case ``i`` of a campaign: (seed file, mutation name, bytes); depends only on its arguments."""
    rng = random.Random(f"{seed}:{fmt}:{i}")
    source, data = rng.choice(blobs)
    name, mutated = mutate(data, fmt, rng)
    return source, name, mutated


def run_campaign(fmt: str, seeds: list[Path], cases: int, *, seed: int = 0, timeout: float = 20.0,
                 memory_limit: int = 4 << 30, workers: int = 2, workdir: Path | None = None,
                 progress: bool = False) -> Campaign:
    """Run ``cases`` mutated files of one format through the readers; returns the tally.

    Case ``i`` is generated from ``(seed, fmt, i)`` alone (reproducible one by one, written just
    before it is read); ``workers`` reader processes share the cases.
    """
    from concurrent.futures import ThreadPoolExecutor

    blobs = [(p, load_seed(p)) for p in seeds]
    # generic CSV files carry no rate: give one, as a user would with --rate
    rate = 100.0 if fmt == "generic_csv" else None
    result = Campaign(cases=cases)
    start = time.perf_counter()
    finished = Counter()
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        def run_share(share: int) -> list[tuple[int, Path, str, dict]]:
            worker, done = Worker(memory_limit), []
            for i in range(share, cases, workers):
                source, name, data = make_case(fmt, blobs, seed, i)
                case = Path(tmp) / f"case_{fmt}_{i}{source.suffix}"
                case.write_bytes(data)
                done.append((i, source, name, worker.read(str(case), timeout, rate)))
                case.unlink()
                finished["n"] += 1
                if progress and finished["n"] % 1000 == 0:
                    print(f"  {fmt}: {finished['n']} cases, {time.perf_counter() - start:.0f} s",
                          flush=True)
            worker.close()
            return done

        with ThreadPoolExecutor(workers) as pool:
            answers = sorted(a for share in pool.map(run_share, range(workers)) for a in share)
    for i, source, name, out in answers:
        outcome = out["outcome"]
        if outcome == "error" and not (out["one_line"] and out["names_file"]):
            outcome = "bad_message"
        result.outcomes[outcome] += 1
        result.mutations[name] += 1
        if outcome not in ("loaded", "error"):
            result.findings.append({"format": fmt, "seed_file": seed_name(source),
                                    "mutation": name, "case": i, **out})
    result.seconds = time.perf_counter() - start
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", type=int, default=10_000, help="cases per format")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--timeout", type=float, default=20.0, help="seconds per case before 'hang'")
    parser.add_argument("--formats", default=",".join(FORMATS))
    parser.add_argument("--workers", type=int, default=2, help="reader processes")
    parser.add_argument("--json", type=Path, help="write the summary here")
    args = parser.parse_args()
    writer_dir = tempfile.TemporaryDirectory(prefix="fuzz_seeds_")
    pools = seed_files(Path(writer_dir.name))
    summary = {}
    for fmt in args.formats.split(","):
        if not pools.get(fmt):
            print(f"{fmt}: no seed files under {SHARED}; skipped")
            continue
        camp = run_campaign(fmt, pools[fmt], args.cases, seed=args.seed, timeout=args.timeout,
                            workers=args.workers, progress=True)
        summary[fmt] = {"cases": camp.cases, "seconds": round(camp.seconds, 1), "seeds": len(pools[fmt]),
                        "outcomes": dict(camp.outcomes), "mutations": dict(camp.mutations),
                        "findings": camp.findings[:50]}
        print(f"{fmt:12s} {camp.cases:6d} cases {camp.seconds:7.1f} s  "
              + "  ".join(f"{k}={v}" for k, v in sorted(camp.outcomes.items())), flush=True)
        for finding in camp.findings[:10]:
            print("   ", json.dumps(finding))
        if args.json:  # after each format: a stopped campaign keeps what it finished
            args.json.write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")


if __name__ == "__main__":
    main()
